"""Onboard tracking (vehicle.tracking) and the matcher's track assignment (assign_tracks).

Hand-built geometry for the rules; fleet passes with the FLEET noise (fixed seeds) for the
tracker's quality, checked within ranges.
"""

from __future__ import annotations

import time
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.noise import FLEET, NoiseModel
from fleetsim.osm_town import helsinki_town
from fleetsim.pipeline import model_for
from fleetsim.synthetic import make_observations
from hdmap.geo.geodesy import direction_from_angles
from hdmap.geo.tiles import quadkeys_of
from hdmap.mapping.association import (
    GateConfig,
    LocalRays,
    angles,
    assign_tracks,
    valid_tracks,
)
from hdmap.mapping.batch_association import associate
from hdmap.mapping.matching import AssocOutput as _Out
from schemas import ObservationBatch, Observations, ObsGroup
from tests.support.association import rays_to
from tests.support.services import matcher
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model
from vehicle.geoloc import Detections, GnssFixes, fix_outliers, geolocate
from vehicle.tracking import TimedRays, TrackConfig, smooth_track, smoothed_rays, track_rays


def _street(gap_images: int = 0) -> tuple[TimedRays, np.ndarray]:
    """Two same-class signs 9 m apart on the right of a straight road, seen together from
    a vehicle at 2 m per image, 5 images a second (3 mrad and 0.3 m of noise, exact ranges
    with a 10 % sigma); sign A is not detected in ``gap_images`` images in the middle."""
    a, b = np.array([4.0, 30.0, 2.5]), np.array([4.0, 39.0, 2.5])
    y = np.arange(12) * 2.0
    origins = np.c_[np.zeros(12), y, np.full(12, 1.4)]
    keep_a = np.ones(12, bool)
    keep_a[5 : 5 + gap_images] = False
    parts, truth = [], []
    rng = np.random.default_rng(0)
    for k, (s, keep) in enumerate(((a, keep_a), (b, np.ones(12, bool)))):
        r = rays_to(np.broadcast_to(s, (keep.sum(), 3)), origins[keep], rng, s_ang=0.003,
                    s_pos=0.3, images=np.flatnonzero(keep))  # fmt: skip
        exact = np.linalg.norm(s - origins[keep], axis=1)
        parts.append(LocalRays(**{**r.__dict__, "range_m": exact, "sigma_range_m": 0.1 * exact}))
        truth += [k] * int(keep.sum())
    rays = LocalRays.concat(parts)
    return TimedRays(**rays.__dict__, t=rays.image * 0.2), np.array(truth)


def test_two_signs_in_view_together_make_two_pure_tracks() -> None:
    rays, truth = _street()
    track = track_rays(rays, TrackConfig())
    assert sorted(Counter(zip(track.tolist(), truth.tolist(), strict=True)).values()) == [12, 12]
    assert np.unique(track).size == 2


def test_a_short_gap_keeps_the_track_and_a_long_one_starts_another() -> None:
    rays, truth = _street(gap_images=3)  # A's last ray before the gap 0.8 s before its next
    assert np.unique(track_rays(rays, TrackConfig(max_gap_s=0.9))[truth == 0]).size == 1
    assert np.unique(track_rays(rays, TrackConfig(max_gap_s=0.7))[truth == 0]).size == 2
    # the times decide, not the image numbers: the same rays 0.1 s apart keep together
    fast = track_rays(rays, TrackConfig(max_gap_s=0.7), t=rays.image * 0.1)
    assert np.unique(fast[truth == 0]).size == 1
    with pytest.raises(ValueError, match=r"^t: "):
        track_rays(LocalRays.concat([rays]), TrackConfig())


def test_smoothing_keeps_a_quadratic_and_shrinks_white_noise() -> None:
    t = np.arange(200) * 0.2
    path = 11.0 * t + 0.3 * t**2  # exact for a local quadratic fit
    assert np.allclose(smooth_track(path, 11), path, atol=1e-9)
    rng = np.random.default_rng(5)
    noisy = path + rng.normal(0.0, 1.0, t.size)
    err = smooth_track(noisy, 11) - path
    assert 0.3 < err[10:-10].std() < 0.7  # 1 m white -> about 0.5 m


def _fleet_passes(n: int):
    world = helsinki_town()
    model = model_for(FLEET, load_vehicle_model())
    cfg = FleetConfig(n_vehicles=5, start_time=1.0e9, route_length_m=(600.0, 1200.0))
    return model, Fleet(world, model, FLEET, cfg, seed=3).passes(n)


def test_tracker_quality_on_fleet_passes(tmp_path: Path) -> None:
    """FLEET noise (1 m white GNSS per fix, 0.01 rad heading, 3 px), the simulator's own
    timing (5 Hz fixes with jitter and misses, 5 Hz frames on their own clock): few rays
    in a track of another sign, few tracks broken within a short gap. Measured on these 5
    passes (index timing, 3,015 rays): 0.3 % and 0.03 per sign and pass; on 20 passes of
    the evaluation fleets (seeds 0 and 1): 0.8-1.4 % and 0.13-0.19; on seed 0's with the
    heading smoothed as well (a mistake found while building it): 1.3 % and 0.71."""
    model, passes = _fleet_passes(5)
    agent = VehicleAgent("veh-q", model, tmp_path)
    cfg = agent.tracking
    assert cfg is not None
    n_rays = impure = breaks = sign_passes = 0
    for k, p in enumerate(passes):
        obs = agent.record(k, p.fixes, p.detections)
        sid, track, t = p.truth.sign_id[agent.last_kept], obs.track.astype(np.int64), obs.t
        n_rays += track.size
        for k in np.unique(track):
            s = sid[track == k]
            impure += s.size - Counter(s.tolist()).most_common(1)[0][1]
        for s in np.unique(sid[sid >= 0]):
            m = np.flatnonzero(sid == s)
            m = m[np.argsort(t[m], kind="stable")]
            gap = np.diff(t[m])
            breaks += int(((np.diff(track[m]) != 0) & (gap <= cfg.max_gap_s)).sum())
            sign_passes += 1
    agent.close()
    assert n_rays > 2000
    assert impure / n_rays < 0.02
    assert breaks / sign_passes < 0.25


def _tracks_per_run(sign_id: np.ndarray, track: np.ndarray, t: np.ndarray, gap_s: float) -> list:
    """Per run of one sign's detections in one pass (a run ends where the sign goes
    undetected for more than ``gap_s``, which no tracker is asked to bridge): how many
    tracks its rays are in. 1 is perfect."""
    out = []
    for s in np.unique(sign_id[sign_id >= 0]):
        m = np.flatnonzero(sign_id == s)
        m = m[np.argsort(t[m], kind="stable")]
        run = np.r_[0, np.cumsum(np.diff(t[m]) > gap_s)]
        out += [np.unique(track[m[run == r]]).size for r in np.unique(run)]
    return out


def _fixes_at_detection_frames(p) -> tuple[GnssFixes, Detections]:
    """The issue's input: 5 Hz frames, a fix only for the frames with detections, in the
    index form (no detection times; ``image`` indexes the fix rows)."""
    frames = np.unique(p.detections.image)
    d = p.detections
    return p.fixes.take(frames), Detections(np.searchsorted(frames, d.image), d.sign_class,
                                            d.box, d.score)  # fmt: skip


def test_three_metres_of_vertical_noise_keep_one_track_per_sign() -> None:
    """Issue 18: fixes only at the frames with detections and 3 m of white vertical noise
    per fix (reported: sigma_v_m = 3) split one sign into 1.9 tracks per pass, as the
    tracker smoothed over fix counts and gated the vertical at a fixed 0.6 m.

    Measured as tracks per run of a sign's detections (runs split at gaps longer than
    ``max_gap_s``, which no tracker bridges) on 6 passes (seed 3, about 290 runs). Bound:
    a mean of at most 1.2, at most one run in five split (a split costs the matcher
    little: two tracks that follow each other may take the same landmark; the issue's
    figure is every sign split). With ~290 runs the split share's binomial std at 0.2 is
    0.024, so the tracker at its measured 1.03 passes by 7 sigma, and the same tracker with
    the old fixed tolerance (measured 1.38) fails by 7."""
    noise = NoiseModel(
        "fleet-v3", replace(FLEET.gnss, white_v_m=3.0, reported_sigma_v_m=3.0), FLEET.detector
    )
    model = model_for(noise, load_vehicle_model())
    cfg = FleetConfig(n_vehicles=5, start_time=1.0e9, route_length_m=(600.0, 1200.0),
                      frame_rate_hz=5.0, fix_per_frame=True)  # fmt: skip
    new, old = TrackConfig(), TrackConfig(sigma_from_fixes=False, rel_pos_sigma_m=0.6)
    runs: dict[str, list] = {"new": [], "old": []}
    for p in Fleet(helsinki_town(), model, noise, cfg, seed=3).passes(6):
        fixes, det = _fixes_at_detection_frames(p)
        assert det.t is None and len(fixes) < len(p.truth.t)
        bad = fix_outliers(fixes)
        keep = ~bad[det.image]
        lines, sid = geolocate(fixes, det, model).take(keep), p.truth.sign_id[keep]
        for name, c in (("new", new), ("old", old)):
            track = track_rays(smoothed_rays(fixes, lines, c, bad), c)
            runs[name] += _tracks_per_run(sid, track, lines.t, c.max_gap_s)
    assert len(runs["new"]) > 250
    assert np.mean(runs["new"]) <= 1.2, np.mean(runs["new"])
    assert np.mean(runs["old"]) > 1.2, np.mean(runs["old"])


def test_a_track_keeps_its_rays_together() -> None:
    """One ray of sign A's track fits B better (a noisy ray): per image it would go to B,
    with its track it stays with A. A track seen at the same time never takes A too."""
    n = 6
    rays = LocalRays(
        *np.zeros((2, n, 3)),
        *np.ones((6, n)),
        image=np.r_[np.arange(5), 2],
        sign_class=np.ones(n, np.int64),
        track=np.array([1, 1, 1, 1, 1, 2]),
    )
    ri = np.array([0, 1, 2, 3, 3, 4, 5, 5])
    li = np.array([0, 0, 0, 0, 1, 0, 0, 1])
    cost = np.array([1.0, 1.5, 2.0, 6.0, 0.5, 1.0, 0.2, 3.0])
    best, unlinked = assign_tracks(rays, ri, li, cost, 13.82, 13.82)
    assert best.tolist() == [0, 0, 0, 0, 0, 1]  # track 2 overlaps track 1: not landmark 0
    assert not unlinked.any()
    best, unlinked = assign_tracks(rays, ri, li, cost, 13.82, 5.0)
    assert best.tolist() == [0, 0, 0, -1, 0, 1] and unlinked.tolist() == [0, 0, 0, 1, 0, 0]


def test_a_track_with_two_rays_in_one_image_is_not_trusted(tmp_path: Path) -> None:
    """A vehicle that labels all its rays one track (two signs in every image) would have
    one landmark take them all (here all 24 go to B's: 12 wrong links); such a track is not
    one sign, so the matcher drops its label and assigns the rays per image."""
    rays, truth = _street()
    x = np.array([[4.0, 30.0, 2.5], [4.0, 39.0, 2.5]])
    cov = np.repeat(np.eye(3)[None], 2, axis=0)
    bogus = np.ones(len(rays), np.int64)
    res = associate(replace(rays, track=bogus), x, cov, np.array([4, 4]), GateConfig())
    assert np.unique(res.landmark).size == 1 and int((res.landmark != truth).sum()) == 12
    fixed = valid_tracks(bogus, rays.image)
    assert not fixed.any()
    res = associate(replace(rays, track=fixed), x, cov, np.array([4, 4]), GateConfig())
    assert (res.landmark == truth).all()
    # the matcher checks a unit's labels as it comes in (two rays per image here): what it
    # keeps (pending, no landmark yet) has the bogus track's label dropped, the other kept
    svc = matcher(tmp_path)
    svc.matching.out = defaultdict(_Out)
    tile = str(quadkeys_of(np.array([60.17]), np.array([24.94]), svc.opts.zoom)[0])
    obs = make_observations(8)
    alternating = (np.arange(8) % 2 + 1).astype(np.uint32)
    for p, track in enumerate((np.ones(8, np.uint32), alternating)):
        unit = replace(obs, obs_id=obs.obs_id + 100 * p, track=track)
        svc._unit(tile, ObsGroup("veh-1", p, p, time.time(), unit))
    assert svc.state.pending[tile].obs.track.tolist() == [0] * 8 + [1, 2] * 4
    assert svc.counters["track_invalid"] == 8


def test_associate_with_tracks_keeps_a_street_of_same_class_signs_apart() -> None:
    """Same street as above, landmarks at the true signs with 2 m sigma, rays without a
    range and with 0.02 rad of angular noise (seed 8): per image, two of sign A's rays fit
    B's landmark better and go there; with the tracks every ray goes to its own sign."""
    rays, truth = _street()
    rng = np.random.default_rng(8)
    az, el = angles(rays.direction)
    noisy = TimedRays(
        **{
            **rays.__dict__,
            "origin": rays.origin + rng.normal(0, 0.3, (24, 3)),
            "direction": direction_from_angles(
                az + rng.normal(0, 0.02, 24), el + rng.normal(0, 0.02, 24)
            ),
            "sigma_az": np.full(24, 0.02),
            "sigma_el": np.full(24, 0.02),
            "range_m": np.zeros(24),
            "sigma_range_m": np.zeros(24),
        }
    )
    x = np.array([[4.0, 30.0, 2.5], [4.0, 39.0, 2.5]])
    cov = np.repeat(4.0 * np.eye(3)[None], 2, axis=0)
    wrong = []
    for track in (None, track_rays(rays, TrackConfig())):
        res = associate(replace(noisy, track=track), x, cov, np.array([4, 4]), GateConfig())
        hit = res.landmark >= 0
        assert hit.sum() >= 20
        wrong.append(int((res.landmark[hit] != truth[hit]).sum()))
    assert wrong[0] >= 1 and wrong[1] == 0, wrong


def test_agent_uploads_tracks_and_an_older_queue_still_reads(tmp_path: Path) -> None:
    model, passes = _fleet_passes(1)
    p = next(iter(passes))
    agent = VehicleAgent("veh-t", model, tmp_path)
    obs = agent.record(0, p.fixes, p.detections)
    assert (obs.track > 0).all() and np.unique(obs.track).size < len(obs) / 4
    # a row queued by a release without the track column (records without it)
    old = Observations.CODEC.to_records(obs.take(np.arange(3)))
    legacy = np.empty(3, Observations.CODEC.base_record_dtype)
    for name in legacy.dtype.names:
        legacy[name] = old[name]
    agent.uploader._db.execute("DELETE FROM outbox")
    agent.uploader._db.executemany(
        "INSERT INTO outbox(obs_id, pass_id, rec) VALUES (?, ?, ?)",
        [(i, 7, legacy[i].tobytes()) for i in range(3)],
    )
    pass_id, back = agent.uploader._oldest_batch()
    assert pass_id == 7 and len(back) == 3 and not back.track.any()
    assert np.array_equal(back.direction, obs.direction[:3])
    sent = ObservationBatch(vehicle_id="veh-t", pass_id=7, batch_id=1, sent_at=1.0e9, obs=back)
    batch = ObservationBatch.from_bytes(sent.to_bytes())
    assert not batch.obs.track.any()
    agent.close()


def test_agent_drops_and_counts_detections_no_fix_reaches(tmp_path: Path) -> None:
    """The simulator's timing; the fixes of a 4 s stretch lost (a tunnel): the detections
    more than max_gap_s (1 s) from every remaining fix are dropped and counted, never
    extrapolated; the rest are queued in their order, with the frames' times."""
    model, passes = _fleet_passes(1)
    p = next(iter(passes))
    det = p.detections
    assert det.t is not None
    near_each = (np.abs(det.t[:, None] - det.t[None, :]) < 1.0).sum(axis=1)
    t, mid = p.fixes.t, float(det.t[np.argmax(near_each)])  # where the detections are
    fixes = p.fixes.take(np.flatnonzero((t < mid - 2.0) | (t > mid + 2.0)))
    far = np.abs(det.t - mid) < 1.0  # farther than 1 s from the fixes left (jitter: 10 ms)
    near = np.abs(det.t - mid) > 1.1
    assert far.sum() > 5
    agent = VehicleAgent("veh-g", model, tmp_path)
    obs = agent.record(0, fixes, det)
    kept = agent.last_kept
    assert not kept[far].any() and agent.dropped_gap >= far.sum()
    assert agent.dropped == int((~kept).sum()) >= agent.dropped_gap
    assert kept[near].mean() > 0.9  # the others: only those of suspect fixes go
    np.testing.assert_array_equal(obs.t, det.t[kept])
    np.testing.assert_array_equal(obs.image, det.image[kept])
    agent.close()
