"""Landmark merge: one sign that became two landmarks becomes one again, in the matcher
(decision, state, persistence) and in the solver (sums handed over, retired landmark
removed from the map). In-process services on real SQLite, through their transactions.

Scene: one sign 30 m north of a road origin; passes drive north along x = -2 m with a
per-pass GNSS bias (1 m per axis) and 0.01 rad angular noise, 10 rays each.
"""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from hdmap.service import ServiceOptions
from hdmap.tiles import quadkeys_of
from schemas import AssocGroup, LandmarkUpdates, Links, LogEntry, NewLandmarks, Observations
from services.matcher.service import MatcherService, _Out
from services.solver.service import SolverService

CLS = 7
SIGN = np.array([10.0, 30.0, 2.5])
LAT, LON = 60.17, 24.94


class Sink:
    """Stands in for the bus: keeps what a service publishes."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, bytes]] = []

    def put(self, key: str, payload: bytes) -> None:
        self.sent.append((key, payload))


def tile_of(zoom: int) -> str:
    return str(quadkeys_of(np.array([LAT]), np.array([LON]), zoom)[0])


def sign_rays(frame, p: int, rng, from_north: bool = False, n: int = 10, image0: int = 0, at=SIGN):
    """One pass's rays at the sign ``at`` (obs ids unique per pass)."""
    ys = np.linspace(0.0, 22.0, n) if not from_north else np.linspace(60.0, 38.0, n)
    a = np.stack([np.full(n, 8.0 if from_north else 12.0), ys, np.full(n, 1.5)], 1)
    a_meas = a + np.r_[rng.normal(0, 1.0, 2), 0.0]  # the pass's shared bias
    v = at - a + rng.normal(0, 0.01, (n, 3)) * np.linalg.norm(at - a, axis=1)[:, None]
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    lat, lon, h = frame.to_geodetic(a_meas)
    return Observations(
        obs_id=(np.arange(n) + 1000 * p + image0).astype(np.uint64),
        t=np.full(n, time.time()),
        image=(np.arange(n) + image0).astype(np.uint32),
        sign_class=np.full(n, CLS, np.uint16),
        lat=lat,
        lon=lon,
        h=h,
        direction=d,  # the frame's ENU; ENU at the camera is within 1e-4 rad of it
        sigma_az=np.full(n, 0.01),
        sigma_el=np.full(n, 0.01),
        sigma_pos_h=np.full(n, 1.0),
        sigma_pos_v=np.full(n, 1.5),
        range_m=np.zeros(n),
        sigma_range_m=np.zeros(n),
        score=np.full(n, 0.9, np.float32),
    )  # fmt: skip


def matcher(path: Path) -> MatcherService:
    svc = MatcherService(ServiceOptions(data_dir=path))
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def two_copies(svc: MatcherService, covisible: bool = False, opposite: bool = False):
    """Landmarks a and b of the one sign: passes 0-5 linked to a, 6-11 to b."""
    rng = np.random.default_rng(3)
    tile = tile_of(svc.opts.zoom)
    frame = svc.frames(tile)
    svc._out = defaultdict(_Out)
    at = frame.to_ecef(
        np.array([SIGN + np.array([1.0, 0.6, 0.0]), SIGN + np.array([-0.9, -0.5, 0.0])])
    )
    a = svc._create(tile, CLS, at[0], np.eye(3) * 4.0)
    b = svc._create(tile, CLS, at[1], np.eye(3) * 4.0)
    for p in range(12):
        obs = sign_rays(frame, p, rng, from_north=opposite and p >= 6)
        if covisible and p < 6:  # the same images also detected a second sign of the class
            both = Observations.concat([obs, sign_rays(frame, p, rng, image0=500)])
            both = Observations(**{**both.__dict__, "image": np.r_[obs.image, obs.image]})
            svc._link(both, [a] * len(obs) + [b] * len(obs), "veh-1", p, time.time())
        else:
            svc._link(obs, [a if p < 6 else b] * len(obs), "veh-1", p, time.time())
    svc._refresh([a.id, b.id])
    return a, b


def test_two_landmarks_of_one_sign_merge_and_the_merge_persists(tmp_path: Path) -> None:
    svc = matcher(tmp_path)
    a, b = two_copies(svc)
    n_before = int(svc.sums.n_obs([a.row])[0] + svc.sums.n_obs([b.row])[0])
    svc._merge_touched([b.id])
    assert list(svc.state.landmarks) == [a.id]  # the older (equal rays: the lower id) stays
    assert int(svc.sums.n_obs([a.row])[0]) == n_before == 120
    assert svc.sums.n_passes([a.row])[0] == 12
    assert svc._out[b.home].retired == [(b.id, a.id)]
    assert np.linalg.norm(svc.frames(a.home).from_ecef(a.x[None])[0] - SIGN) < 1.5
    with svc.transaction([svc]):
        svc.state.save(svc.sums.pack_rows)
    again = matcher(tmp_path)
    assert list(again.state.landmarks) == [a.id]
    assert int(again.sums.n_obs([again.state.landmarks[a.id].row])[0]) == 120
    np.testing.assert_allclose(again.state.landmarks[a.id].view, a.view)
    assert again.state.covis == {}


@pytest.mark.parametrize("kind", ["covisible", "opposite"])
def test_landmarks_seen_together_or_from_opposite_sides_stay_apart(tmp_path, kind) -> None:
    svc = matcher(tmp_path)
    a, b = two_copies(svc, covisible=kind == "covisible", opposite=kind == "opposite")
    if kind == "covisible":
        assert svc.state.covis_count(a.id, b.id) == 60
    svc._merge_touched([a.id, b.id])
    assert sorted(svc.state.landmarks) == sorted([a.id, b.id])
    assert not svc._out[a.home].retired


def solver(path: Path) -> SolverService:
    svc = SolverService(ServiceOptions(data_dir=path))
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def assoc_entry(seq: int, tile: str, **kw) -> LogEntry:
    g = AssocGroup(
        vehicles=kw.get("vehicles", []),
        links=kw.get("links", Links.empty()),
        obs=kw.get("obs", Observations.empty()),
        created=kw.get("created", NewLandmarks.empty()),
        retired=np.array(kw.get("retired", []), np.uint64),
        merged_into=np.array(kw.get("merged_into", []), np.uint64),
    )
    return LogEntry("assoc", "matcher-test", tile, seq, seq, g.to_bytes())


def updates(svc: SolverService) -> list[LandmarkUpdates]:
    out = [LandmarkUpdates.from_bytes(LogEntry.from_bytes(p).body) for _k, p in svc.pubs.sent]
    svc.pubs.sent.clear()
    return out


def test_solver_hands_the_sums_over_and_the_map_drops_the_retired(tmp_path: Path) -> None:
    zoom = ServiceOptions().zoom
    tile = tile_of(zoom)
    m = matcher(tmp_path / "m")  # for ids and frames only
    frame = m.frames(tile)
    rng = np.random.default_rng(5)
    obs = [sign_rays(frame, p, rng) for p in range(12)]
    ida, idb = m.state.next_id(tile), m.state.next_id(tile)
    lat, lon, h = frame.to_geodetic((SIGN + np.array([0.5, 0.5, 0.0]))[None])
    created = NewLandmarks(
        np.array([ida, idb], np.uint64), np.full(2, CLS, np.uint16), np.r_[lat, lat],
        np.r_[lon, lon], np.r_[h, h],
    )  # fmt: skip

    def links(ids: list[int], passes: range) -> dict:
        o = Observations.concat([obs[p] for p in passes])
        return {
            "vehicles": ["veh-1"],
            "obs": o,
            "links": Links(
                np.repeat(np.array(ids, np.uint64), 10),
                np.zeros(len(o), np.uint32),
                np.repeat(np.array(list(passes), np.uint64), 10),
                np.full(len(o), time.time()),
                np.ones(len(o), np.float32),
            ),
        }

    s = solver(tmp_path / "s")
    s._apply_in_transaction(
        [assoc_entry(1, tile, created=created, **links([ida] * 6 + [idb] * 6, range(12)))]
    )
    first = updates(s)
    assert sorted(first[0].landmarks.id.tolist()) == sorted([ida, idb])  # both published
    s._apply_in_transaction([assoc_entry(2, tile, retired=[idb], merged_into=[ida])])
    (u,) = updates(s)
    assert u.removed.id.tolist() == [idb]
    assert u.landmarks.id.tolist() == [ida]
    assert int(u.landmarks.n_obs[0]) == 120 and int(u.landmarks.n_passes[0]) == 12
    assert sorted(s.state.landmarks) == [ida]
    # the same rays given to one landmark from the start: the same estimate
    one = solver(tmp_path / "one")
    one._apply_in_transaction(
        [assoc_entry(1, tile, created=created.take(np.array([0])), **links([ida] * 12, range(12)))]
    )
    (ref,) = updates(one)
    np.testing.assert_allclose(u.landmarks.lat, ref.landmarks.lat, rtol=0, atol=1e-11)
    np.testing.assert_allclose(u.landmarks.lon, ref.landmarks.lon, rtol=0, atol=1e-11)
    np.testing.assert_allclose(u.landmarks.cov, ref.landmarks.cov, rtol=1e-8, atol=1e-12)
    # after a restart the retired landmark is gone for good; unknown ids are rejected
    again = solver(tmp_path / "s")
    assert sorted(again.state.landmarks) == [ida]
    again._apply_in_transaction([assoc_entry(3, tile, retired=[idb], merged_into=[ida])])
    assert again.rejected["assoc.unknown_retired"] == 1
