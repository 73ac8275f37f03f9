"""A vehicle that follows the map reports the mapped signs it should have seen and did not
(issue 21, vehicle side): :mod:`vehicle.absence_report`, the agent's ``record`` and the
uploader's absences queue.

The drive: a simulated pass (fixed seeds, ``fleetsim.drive.simulate_pass``) north along a
straight road (x = 0, lane 1.75 m east, y from -100 to 200 m) past five mapped signs, all
4 m right of the lane: A (y = 20, facing the car: detected), B (y = 80, facing the car:
its detections removed, the sign gone), C (y = -130: behind the camera all the way), D
(y = 250: ahead, beyond the road's end, never within range) and E (y = 140, facing north:
the car sees its back). The map is the truth (0.1 m^2 covariance, facing known).

The upload path runs without an ingest: the uploader's ``_send`` is replaced by a fake
that decodes each batch from its bytes (``ObservationBatch.from_bytes``) and answers.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetsim.drive import DriveParams, simulate_pass
from fleetsim.noise import EXACT, FLEET, NoiseModel
from fleetsim.pipeline import model_for
from fleetsim.route import Path as RoutePath
from fleetsim.synthetic import make_observations
from fleetsim.world import HELSINKI, Signs, World
from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.signs import CATALOG
from schemas import (
    STATUS_CONFIRMED,
    STATUS_RETIRED,
    Absences,
    ObservationBatch,
    Rejection,
    UploadAck,
)
from schemas.map import MapLandmarks
from tests.support import Clock
from vehicle.absence_report import (
    AbsenceConfig,
    detection_bearings,
    mounting_yaw_deg,
    pass_absences,
    view_model,
)
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model
from vehicle.geoloc import Detections, GnssFixes, fix_outliers
from vehicle.uploader import Uploader

A, B, C, D, E = 10, 11, 12, 13, 14
MODEL = model_for(FLEET, load_vehicle_model())
_ROWS = (  # id, class, y, facing (the direction it is seen from)
    (A, "stop", 20.0, 180.0),
    (B, "give_way", 80.0, 180.0),
    (C, "no_entry", -130.0, 180.0),
    (D, "children", 250.0, 180.0),
    (E, "bus_stop", 140.0, 0.0),
)
SIGNS = Signs.build(
    [CATALOG.code(r[1]) for r in _ROWS],
    [[1.75 + 4.0, r[2], 2.4] for r in _ROWS],
    [r[3] for r in _ROWS],
    ids=[r[0] for r in _ROWS],
)
WORLD = World(
    EnuFrame(*HELSINKI), np.array([[0.0, -100.0], [0.0, 200.0]]), np.array([[0, 1]]), SIGNS
)


def drive(
    seed: int, noise: NoiseModel = FLEET, params: DriveParams | None = None
) -> tuple[GnssFixes, Detections, np.ndarray]:
    """The pass, without the detections of B (gone) and D (too far for the detector):
    fixes, detections, and the true sign of each detection (-1: a false positive)."""
    path = RoutePath.along(WORLD, [0, 1])
    rng = np.random.default_rng(seed)
    fixes, det, truth = simulate_pass(WORLD, path, MODEL, noise, rng, t0=1.0e9, params=params)
    keep = np.flatnonzero(~np.isin(truth.sign_id, [B, D]))
    return fixes, det.take(keep), truth.sign_id[keep]


def the_map(status: int = STATUS_CONFIRMED) -> MapLandmarks:
    """The five signs as the map publishes them."""
    lat, lon, h = WORLD.signs_geodetic()
    n = len(SIGNS)
    return MapLandmarks(
        id=SIGNS.id.astype(np.uint64),
        sign_class=SIGNS.sign_class.astype(np.uint16),
        lat=lat,
        lon=lon,
        h=h,
        cov=np.tile([0.1, 0.0, 0.0, 0.1, 0.0, 0.1], (n, 1)),
        status=np.full(n, status, np.uint8),
        n_obs=np.full(n, 50, np.uint32),
        n_passes=np.full(n, 5, np.uint32),
        revision=np.ones(n, np.uint64),
        updated_at=np.full(n, 1.0e9),
        source_time=np.full(n, 1.0e9),
        facing_deg=SIGNS.facing_azimuth_deg.astype(np.float32),
        facing_sigma_deg=np.full(n, 5.0, np.float32),
    )


# --- which signs -------------------------------------------------------------------------


@pytest.mark.parametrize(("noise", "seed"), [(EXACT, 0), (FLEET, 1), (FLEET, 2), (FLEET, 3)])
def test_the_sign_driven_past_and_not_detected_is_reported_with_its_view(noise, seed):
    fixes, det, sign = drive(seed, noise)
    assert (sign == A).sum() > 10  # A was detected, and is not reported
    ab = pass_absences(fixes, det, the_map(), MODEL)
    assert ab.landmark_id.tolist() == [B]
    view = view_model(MODEL)
    # In view from 35 m to where it leaves the field of view (4 m right: about 7 m off),
    # some 28 m at 11 m/s: 2.5 s of 5 Hz fixes; the closest view at the edge, on the right.
    assert 8 <= int(ab.frames[0]) <= 20
    usable = len(fixes) - int(fix_outliers(fixes).sum())  # multipath fixes are not frames
    assert ab.share[0] == pytest.approx(ab.frames[0] / usable, rel=1e-6)
    assert view.min_range_m <= ab.range_m[0] <= 12.0
    assert 10.0 <= ab.bearing_deg[0] <= view.hfov_deg / 2.0 + 1e-3
    y_b = 80.0
    t_pass = fixes.t[
        np.argmin(np.abs(WORLD.frame.from_geodetic(fixes.lat, fixes.lon, fixes.h)[:, 1] - y_b))
    ]
    assert t_pass - 2.0 < ab.t[0] < t_pass  # just before the car passes it
    # the wire's checks hold
    bad, _, _ = Absences.CODEC.row_errors(ab)
    assert not bad.any()


def test_signs_behind_beyond_range_or_facing_away_are_not_reported_for_that_reason():
    """Each excluded sign is reported once its own rule is lifted (and C never: behind)."""
    fixes, det, _ = drive(1)
    lm = the_map()
    far = AbsenceConfig(max_range_m=70.0, match_range_m=70.0)
    assert pass_absences(fixes, det, lm, MODEL, far).landmark_id.tolist() == [B, D]
    back = AbsenceConfig(facing_tol_deg=180.0)
    assert pass_absences(fixes, det, lm, MODEL, back).landmark_id.tolist() == [B, E]
    unknown = replace(lm, facing_sigma_deg=np.zeros(len(lm), np.float32))  # facing unknown
    assert pass_absences(fixes, det, unknown, MODEL).landmark_id.tolist() == [B, E]


def test_a_blind_pass_reports_every_sign_in_view_and_retired_ones_never():
    fixes, det, _ = drive(1)
    none = det.take(np.zeros(0, np.int64))
    assert pass_absences(fixes, none, the_map(), MODEL).landmark_id.tolist() == [A, B]
    assert len(pass_absences(fixes, none, the_map(STATUS_RETIRED), MODEL)) == 0
    assert len(pass_absences(fixes, det, MapLandmarks.empty(), MODEL)) == 0


def test_a_detection_off_the_gate_does_not_count_and_the_gate_grows_with_the_pose_sigma():
    """A's detections turned 20 degrees clockwise (another sign of its class): A is
    reported; with fixes that claim an 8 degree heading sigma the gate (3 sigmas) takes
    them again. Exact fixes that claim 5 cm and 0.05 degrees (RTK), no floors."""
    fixes, det, sign = drive(1, EXACT)
    n = len(fixes)
    fixes = replace(fixes, sigma_h_m=np.full(n, 0.05), sigma_heading_deg=np.full(n, 0.05))
    cfg = AbsenceConfig(pose_sigma_floor_m=0.0, heading_sigma_floor_deg=0.0, gate_sigmas=3.0)
    intr = MODEL.intrinsics
    turn = np.where(sign == A, np.radians(20.0), 0.0)
    uc = (det.box[:, 0] + det.box[:, 2]) / 2.0
    du = intr.cx + intr.fx * np.tan(np.arctan((uc - intr.cx) / intr.fx) + turn) - uc
    moved = replace(det, box=det.box + du[:, None] * np.array([1.0, 0.0, 1.0, 0.0]))
    assert pass_absences(fixes, det, the_map(), MODEL, cfg).landmark_id.tolist() == [B]
    assert pass_absences(fixes, moved, the_map(), MODEL, cfg).landmark_id.tolist() == [A, B]
    unsure = replace(fixes, sigma_heading_deg=np.full(n, 8.0))
    assert pass_absences(unsure, moved, the_map(), MODEL, cfg).landmark_id.tolist() == [B]


def test_the_index_form_one_fix_per_frame_without_times():
    fixes, det, _ = drive(2, FLEET, DriveParams(fix_per_frame=True))
    det = replace(det, t=None)  # image numbers index the fixes
    assert pass_absences(fixes, det, the_map(), MODEL).landmark_id.tolist() == [B]


def test_the_view_and_the_bearings_come_from_the_camera_model():
    view = view_model(MODEL)
    intr = MODEL.intrinsics
    hfov = 2.0 * np.degrees(np.arctan(intr.width / 2.0 / intr.fx))
    assert view.hfov_deg == pytest.approx(hfov - 2.0 * AbsenceConfig().fov_margin_deg)
    assert mounting_yaw_deg(MODEL) == pytest.approx(0.0, abs=1e-9)
    u = intr.cx + intr.fx * np.tan(np.radians([0.0, 20.0, -30.0]))
    box = np.column_stack([u - 5.0, np.full(3, 500.0), u + 5.0, np.full(3, 510.0)])
    det = Detections(np.zeros(3, np.int64), np.full(3, 4), box, np.ones(3))
    # the box centre's row is off the principal point's: the azimuth is still the column's
    np.testing.assert_allclose(detection_bearings(det, MODEL), [0.0, 20.0, -30.0], atol=1e-6)


# --- the queue ---------------------------------------------------------------------------


def absences(ids: list[int], t: float = 1.0e9) -> Absences:
    n = len(ids)
    return Absences(
        landmark_id=np.array(ids, np.uint64),
        t=np.full(n, t),
        frames=np.full(n, 12, np.uint32),
        share=np.full(n, 0.1, np.float32),
        range_m=np.full(n, 8.0, np.float32),
        bearing_deg=np.full(n, 25.0, np.float32),
    )


class FakeIngest:
    """Decodes every batch from its bytes, keeps it, and acks it whole (or as told)."""

    def __init__(self, answer=None):
        self.batches: list[ObservationBatch] = []
        self.answer = answer

    def __call__(self, _session, batch: ObservationBatch, _timeout: float) -> UploadAck | None:
        got = ObservationBatch.from_bytes(batch.to_bytes())
        self.batches.append(got)
        if self.answer is not None:
            return self.answer(got)
        return UploadAck("veh-1", got.batch_id, got.obs.obs_id, absences=len(got.absences))


def test_absences_survive_a_restart_and_go_once_with_the_pass_s_last_batch(tmp_path, monkeypatch):
    path = tmp_path / "q.sqlite"
    up = Uploader("veh-1", path, batch_size=5, clock=Clock())
    up.enqueue(1, make_observations(7, seed=1), absences([21, 22]))
    up.close()

    up = Uploader("veh-1", path, batch_size=5, clock=Clock())  # the vehicle restarted
    assert (up.pending, up.pending_absences) == (7, 2)
    ingest = FakeIngest()
    monkeypatch.setattr(up, "_send", ingest)
    res = up.flush(None)
    assert [(len(b.obs), len(b.absences)) for b in ingest.batches] == [(5, 0), (2, 2)]
    got = ingest.batches[1].absences
    assert got.landmark_id.tolist() == [21, 22] and ingest.batches[1].pass_id == 1
    np.testing.assert_array_equal(got.frames, [12, 12])
    np.testing.assert_allclose(got.bearing_deg, [25.0, 25.0])
    assert (res.absences_sent, res.absences_recorded, res.absences_rejected) == (2, 2, 0)
    assert res.absences_unrecorded == 0 and up.pending_absences == 0
    assert up.flush(None).sent == 0 and len(ingest.batches) == 2  # sent once
    up.close()


def test_a_pass_whose_observations_are_uploaded_sends_its_absences_alone(tmp_path, monkeypatch):
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=3, clock=Clock())
    ingest = FakeIngest()
    monkeypatch.setattr(up, "_send", ingest)
    up.enqueue(1, make_observations(2, seed=1))
    assert up.flush(None).accepted == 2
    up.enqueue(1, make_observations(0), absences([31, 32, 33, 34]))  # the pass's report
    res = up.flush(None)
    assert [(b.pass_id, len(b.obs), len(b.absences)) for b in ingest.batches[1:]] == [
        (1, 0, 3),
        (1, 0, 1),
    ]  # capped per batch like the observations
    assert res.sent == 0 and (res.absences_sent, res.absences_recorded) == (4, 4)
    assert up.pending_absences == 0
    # the batch of absences alone round-trips (the fake decoded it from its bytes too)
    alone = ingest.batches[1]
    back = ObservationBatch.from_bytes(alone.to_bytes())
    assert len(back.obs) == 0 and back.absences.landmark_id.tolist() == [31, 32, 33]
    up.close()


def test_refused_absences_are_counted_by_field_kept_and_leave_the_observations_alone(
    tmp_path, monkeypatch, caplog
):
    """The refused absence's landmark id (3) is also a queued observation's id: that
    observation stays queued (the refusal is the absence's)."""
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=10, clock=Clock())
    up.enqueue(1, make_observations(4, seed=1), absences([3, 5]))

    def answer(b: ObservationBatch) -> UploadAck:
        bad = [Rejection(3, "absences.t", "captured 400 s in the future")]
        return UploadAck("veh-1", b.batch_id, b.obs.obs_id[:2], rejected=bad, absences=1)

    monkeypatch.setattr(up, "_send", FakeIngest(answer))
    with caplog.at_level(logging.WARNING, logger="vehicle.uploader"):
        res = up.flush(None, max_batches=1)
    assert (res.accepted, res.rejected, res.rejected_by) == (2, 0, {})
    assert (res.absences_recorded, res.absences_rejected) == (1, 1)
    assert res.absences_rejected_by == {"absences.t": 1}
    assert up.pending == 2 and up.pending_absences == 0  # obs 3 and 4 still queued
    assert up.rejected() == []
    assert up.rejected_absences() == [
        (1, Rejection(3, "absences.t", "captured 400 s in the future"))
    ]
    assert any(
        "refused 1 absence(s) of batch 1 on absences.t" in r.getMessage() for r in caplog.records
    )
    up.close()


def test_a_batch_without_an_answer_keeps_its_absences_and_an_ingest_that_ignores_them_is_said(
    tmp_path, monkeypatch, caplog
):
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=10, clock=Clock())
    up.enqueue(1, make_observations(0), absences([41, 42]))
    lost = FakeIngest(lambda b: None)  # a timeout
    monkeypatch.setattr(up, "_send", lost)
    res = up.flush(None)
    assert res.failed_batches == 1 and res.absences_sent == 2 and up.pending_absences == 2

    older = FakeIngest(lambda b: UploadAck("veh-1", b.batch_id, b.obs.obs_id))  # no absences
    monkeypatch.setattr(up, "_send", older)
    with caplog.at_level(logging.WARNING, logger="vehicle.uploader"):
        res = up.flush(None)
    assert res.absences_unrecorded == 2 and res.absences_recorded == 0
    assert up.pending_absences == 0  # not sent again
    assert any("neither recorded nor refused 2" in r.getMessage() for r in caplog.records)
    up.close()


# --- the agent ---------------------------------------------------------------------------


def test_the_agent_queues_a_pass_s_absences_with_it_and_uploads_them_after_a_restart(
    tmp_path: Path, monkeypatch
):
    fixes, det, _ = drive(3)
    agent = VehicleAgent("veh-1", MODEL, tmp_path, batch_size=20)
    obs = agent.record(5, fixes, det, expected_map=the_map())
    assert agent.last_absences.landmark_id.tolist() == [B]
    agent.record(6, fixes, det)  # no map: no absences
    assert len(agent.last_absences) == 0
    agent.close()

    agent = VehicleAgent("veh-1", MODEL, tmp_path, batch_size=20)
    assert agent.uploader.pending_absences == 1
    ingest = FakeIngest()
    monkeypatch.setattr(agent.uploader, "_send", ingest)
    res = agent.upload(None)
    with_absences = [b for b in ingest.batches if len(b.absences)]
    assert len(with_absences) == 1 and with_absences[0].pass_id == 5
    last_of_pass = [b for b in ingest.batches if b.pass_id == 5][-1]
    assert last_of_pass is with_absences[0]  # with the pass's last batch
    assert sum(len(b.obs) for b in ingest.batches if b.pass_id == 5) == len(obs)
    assert (res.absences_sent, res.absences_recorded, agent.uploader.pending_absences) == (1, 1, 0)
    agent.close()
