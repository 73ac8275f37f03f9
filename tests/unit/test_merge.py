"""Landmark merge: one sign that became two landmarks becomes one again, in the matcher
(decision, state, persistence) and in the solver (sums handed over, retired landmark
removed from the map). In-process services on real SQLite, through their transactions.

Scene: one sign 30 m north of a road origin; passes drive north along x = -2 m with a
per-pass GNSS bias (1 m per axis) and 0.01 rad angular noise, 10 rays each.
"""

from __future__ import annotations

import dataclasses
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from fleetsim.synthetic import ray_observations
from hdmap.mapping.linking import create, link, refresh
from hdmap.mapping.matching import AssocOutput as _Out
from hdmap.mapping.merge import merge_touched
from hdmap.runtime.service import ServiceOptions
from schemas import Links, NewLandmarks, Observations
from services.matcher.service import MatcherService
from services.solver.service import SolverConfig
from tests.support.services import (
    CLS,
    SIGN,
    assoc_entry,
    matcher,
    sign_rays,
    solver,
    tile_of,
    updates,
)


def two_copies(svc: MatcherService, covisible: bool = False, opposite: bool = False):
    """Landmarks a and b of the one sign: passes 0-5 linked to a, 6-11 to b."""
    rng = np.random.default_rng(3)
    tile = tile_of(svc.opts.zoom)
    frame = svc.frames(tile)
    svc.matching.out = defaultdict(_Out)
    at = frame.to_ecef(
        np.array([SIGN + np.array([1.0, 0.6, 0.0]), SIGN + np.array([-0.9, -0.5, 0.0])])
    )
    a = create(svc.matching, tile, CLS, at[0], np.eye(3) * 4.0)
    b = create(svc.matching, tile, CLS, at[1], np.eye(3) * 4.0)
    for p in range(12):
        obs = sign_rays(frame, p, rng, from_north=opposite and p >= 6)
        if covisible and p < 6:  # the same images also detected a second sign of the class
            both = Observations.concat([obs, sign_rays(frame, p, rng, image0=500)])
            both = Observations(**{**both.__dict__, "image": np.r_[obs.image, obs.image]})
            link(svc.matching, both, [a] * len(obs) + [b] * len(obs), "veh-1", p, time.time())
        else:
            link(svc.matching, obs, [a if p < 6 else b] * len(obs), "veh-1", p, time.time())
    refresh(svc.matching, [a.id, b.id])
    return a, b


def test_two_landmarks_of_one_sign_merge_and_the_merge_persists(tmp_path: Path) -> None:
    svc = matcher(tmp_path)
    a, b = two_copies(svc)
    n_before = int(svc.sums.n_obs([a.row])[0] + svc.sums.n_obs([b.row])[0])
    merge_touched(svc.matching, [b.id])
    assert list(svc.state.landmarks) == [a.id]  # the older (equal rays: the lower id) stays
    assert int(svc.sums.n_obs([a.row])[0]) == n_before == 120
    assert svc.sums.n_passes([a.row])[0] == 12
    assert svc.matching.out[b.home].retired == [(b.id, a.id)]
    assert np.linalg.norm(svc.frames(a.home).from_ecef(a.x[None])[0] - SIGN) < 1.5
    with svc.transaction([svc]):
        svc.state.save(svc.sums.pack_rows)
    again = matcher(tmp_path)
    assert list(again.state.landmarks) == [a.id]
    assert int(again.sums.n_obs([again.state.landmarks[a.id].row])[0]) == 120
    np.testing.assert_allclose(again.state.landmarks[a.id].view, a.view)
    assert again.state.covis == {}


def test_a_far_loose_landmark_with_the_smallest_chi2_does_not_hide_the_partner(
    tmp_path: Path,
) -> None:
    """A third landmark of the class 15 m away with a 100 m sigma has a smaller chi-square
    against ``b`` than ``a`` has, but is beyond ``merge_max_m``: ``b`` still finds ``a``."""
    from hdmap.mapping.merge import merge_partner

    svc = matcher(tmp_path)
    a, b = two_copies(svc)
    frame = svc.frames(tile_of(svc.opts.zoom))
    far = create(
        svc.matching,
        tile_of(svc.opts.zoom),
        CLS,
        frame.to_ecef((SIGN + np.array([9.0, 12.0, 0.0]))[None])[0],
        np.eye(3) * 1e4,
    )
    rng = np.random.default_rng(5)
    for p in range(12, 14):  # two passes: enough to be a merge candidate
        link(svc.matching, sign_rays(frame, p, rng), [far] * 10, "veh-2", p, time.time())
    d = (np.array([a.x, far.x]) - b.x) @ frame.rotation.T
    c = b.cov[None] + np.array([a.cov, far.cov])
    chi2 = np.einsum("ki,ki->k", d, np.linalg.solve(c, d[:, :, None])[:, :, 0])
    assert chi2[1] < chi2[0] <= svc.matching.config.merge_chi2
    assert np.hypot(*d[1, :2]) > svc.matching.config.merge_max_m
    assert merge_partner(svc.matching, b) is a


@pytest.mark.parametrize("kind", ["covisible", "opposite"])
def test_landmarks_seen_together_or_from_opposite_sides_stay_apart(tmp_path, kind) -> None:
    svc = matcher(tmp_path)
    a, b = two_copies(svc, covisible=kind == "covisible", opposite=kind == "opposite")
    if kind == "covisible":
        assert svc.state.covis_count(a.id, b.id) == 60
    merge_touched(svc.matching, [a.id, b.id])
    assert sorted(svc.state.landmarks) == sorted([a.id, b.id])
    assert not svc.matching.out[a.home].retired


def split_passes(svc: MatcherService, covisible: bool = False, from_north_b: bool = False):
    """Landmarks a and b of the one sign, every pass's near rays linked to a and its far
    ones to b in one unit (a copy made of a sign's own rays); then b's gating estimate
    moved 8 m along the road, both with tight covariances (as a biased subset of the
    passes gives them), so that the estimates alone refuse the merge. ``covisible``: b's rays are in
    the images of a's; ``from_north_b``: b is seen from the opposite direction."""
    rng = np.random.default_rng(4)
    tile = tile_of(svc.opts.zoom)
    frame = svc.frames(tile)
    svc.matching.out = defaultdict(_Out)
    at = frame.to_ecef(np.array([SIGN, SIGN + np.array([0.0, 8.0, 0.0])]))
    a = create(svc.matching, tile, CLS, at[0], np.eye(3) * 4.0)
    b = create(svc.matching, tile, CLS, at[1], np.eye(3) * 4.0)
    for p in range(12):
        near = sign_rays(frame, p, rng)
        far = sign_rays(frame, p, rng, from_north=from_north_b, image0=0 if covisible else 500)
        both = Observations.concat([near, far])
        link(svc.matching, both, [a] * len(near) + [b] * len(far), "veh-1", p, time.time())
    refresh(svc.matching, [a.id, b.id])
    a.cov, b.x, b.cov = np.eye(3) * 0.04, at[1], np.eye(3) * 0.04
    return a, b


@pytest.mark.parametrize("kind", ["copy", "covisible", "facing", "off"])
def test_a_copy_linked_by_the_same_passes_merges_whatever_its_estimate(tmp_path, kind) -> None:
    """Co-passes and no co-visibility make b a copy of a though 8 m and 40 sigma apart;
    seen in a's images, from the other side, or with the copy merge off, it stays apart."""
    from hdmap.mapping.merge import merge_partner

    svc = matcher(tmp_path)
    if kind == "off":
        svc.matching.config = dataclasses.replace(
            svc.matching.config, merge_copy_units=0, merge_apart_max_m=0.0
        )
    a, b = split_passes(svc, covisible=kind == "covisible", from_north_b=kind == "facing")
    assert svc.state.copass.get(a.id, b.id) == 12
    assert svc.state.covis_count(a.id, b.id) == (120 if kind == "covisible" else 0)
    want = a if kind == "copy" else None
    assert merge_partner(svc.matching, b) is want
    merge_touched(svc.matching, [b.id])
    assert sorted(svc.state.landmarks) == ([a.id] if kind == "copy" else sorted([a.id, b.id]))
    with svc.transaction([svc]):
        svc.state.save(svc.sums.pack_rows)
    again = matcher(tmp_path)
    assert again.state.copass.counts == svc.state.copass.counts


def apart_passes(svc: MatcherService, kind: str):
    """Landmarks a and b of the one sign, passes 0-9 linked to a and 10-19 to b (no pass
    links to both); then b's gating estimate moved 5 m along the road (9 m: ``far``), both
    with tight covariances, as two routes with different biases give them. ``covisible``:
    passes 0-9 also detected a second sign of the class in their images, linked to b;
    ``facing``: b is seen from the opposite direction; ``few``: 6 rays a pass."""
    rng = np.random.default_rng(6)
    tile = tile_of(svc.opts.zoom)
    frame = svc.frames(tile)
    svc.matching.out = defaultdict(_Out)
    off = SIGN + np.array([0.0, 9.0 if kind == "far" else 5.0, 0.0])
    at = frame.to_ecef(np.array([SIGN, off]))
    a = create(svc.matching, tile, CLS, at[0], np.eye(3) * 4.0)
    b = create(svc.matching, tile, CLS, at[1], np.eye(3) * 4.0)
    n = 6 if kind == "few" else 10
    for p in range(20):
        obs = sign_rays(frame, p, rng, from_north=kind == "facing" and p >= 10, n=n)
        if kind == "covisible" and p < 10:
            both = Observations.concat([obs, sign_rays(frame, p, rng, n=n, image0=500)])
            both = Observations(**{**both.__dict__, "image": np.r_[obs.image, obs.image]})
            link(svc.matching, both, [a] * n + [b] * n, "veh-1", p, time.time())
        else:
            link(svc.matching, obs, [a if p < 10 else b] * n, "veh-1", p, time.time())
    refresh(svc.matching, [a.id, b.id])
    a.cov, b.x, b.cov = np.eye(3) * 0.04, at[1], np.eye(3) * 0.04
    return a, b


@pytest.mark.parametrize("kind", ["apart", "covisible", "facing", "few", "far", "off"])
def test_a_copy_seen_from_other_passes_merges_when_never_in_one_image(tmp_path, kind) -> None:
    """No pass links both and the estimates are 5 m and 18 sigma apart: never in one image,
    facing one way, each with 100 rays, b is a copy of a. In a's images, from the other
    side, with 60 rays each, 9 m apart, or with the rule off, it stays apart."""
    from hdmap.mapping.merge import merge_partner

    svc = matcher(tmp_path)
    if kind == "off":
        svc.matching.config = dataclasses.replace(svc.matching.config, merge_apart_max_m=0.0)
    a, b = apart_passes(svc, kind)
    assert svc.state.copass.get(a.id, b.id) == (10 if kind == "covisible" else 0)
    assert svc.state.covis_count(a.id, b.id) == (100 if kind == "covisible" else 0)
    assert merge_partner(svc.matching, b) is (a if kind == "apart" else None)
    before = svc.counters["merged_apart"]
    merge_touched(svc.matching, [b.id])
    assert sorted(svc.state.landmarks) == ([a.id] if kind == "apart" else sorted([a.id, b.id]))
    assert svc.counters["merged_apart"] - before == (1 if kind == "apart" else 0)


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
    # a merge in a group of its own (the matcher merges when a gating tick ends): the
    # update's source time is the solver's clock, not 0 (a latency of 56 years)
    assert u.landmarks.source_time[0] > time.time() - 3600.0
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
    # the solver's sums drop the merged row at the save (compact_min_rows 1) or keep it
    # (the default); more rays then give the same bits
    small = solver(tmp_path / "c", SolverConfig(compact_min_rows=1))
    last = []
    for svc in (s, small):
        if svc is small:
            svc._apply_in_transaction(
                [assoc_entry(1, tile, created=created, **links([ida] * 6 + [idb] * 6, range(12)))]
            )
            svc._apply_in_transaction([assoc_entry(2, tile, retired=[idb], merged_into=[ida])])
        assert len(svc.sums) == (1 if svc is small else 2)
        svc._apply_in_transaction([assoc_entry(3, tile, **links([ida] * 3, range(9, 12)))])
        last.append(updates(svc)[-1].landmarks)
    assert last[0].lat.tobytes() == last[1].lat.tobytes()
    assert last[0].cov.tobytes() == last[1].cov.tobytes()
    # after a restart the retired landmark is gone for good; unknown ids are rejected
    again = solver(tmp_path / "s")
    assert sorted(again.state.landmarks) == [ida]
    again._apply_in_transaction([assoc_entry(3, tile, retired=[idb], merged_into=[ida])])
    assert again.rejected["assoc.unknown_retired"] == 1


def test_landmarks_seen_from_streets_at_right_angles_merge_only_at_one_place(
    tmp_path: Path,
) -> None:
    """Two landmarks of the class 1.5 m apart (well inside the merge gate), one seen from
    the road to the South of the sign, one from a street to its East: their facings
    (:mod:`hdmap.mapping.facing`) are 90 degrees apart, beyond 60 + sigmas, so they are
    two signs when farther apart than ``same_place_m`` (here set to 1 m), and one sign
    seen from two streets closer than it (the default 3 m); with any side allowed they
    merge either way (the facing is what decides)."""
    from hdmap.mapping.facing import angle_between
    from hdmap.mapping.matching import facings_of
    from hdmap.mapping.merge import merge_partner

    svc = matcher(tmp_path)
    rng = np.random.default_rng(3)
    tile = tile_of(svc.opts.zoom)
    frame = svc.frames(tile)
    svc.matching.out = defaultdict(_Out)
    at = frame.to_ecef(
        np.array([SIGN + np.array([1.0, 0.6, 0.0]), SIGN + np.array([-0.4, -0.3, 0.0])])
    )
    a = create(svc.matching, tile, CLS, at[0], np.eye(3) * 4.0)
    b = create(svc.matching, tile, CLS, at[1], np.eye(3) * 4.0)
    for p in range(12):
        if p < 6:
            obs = sign_rays(frame, p, rng)
        else:  # westbound on y = 32.5, 40 m to 18 m east of the sign
            xs = np.linspace(50.0, 28.0, 10)
            cam = np.stack([xs, np.full(10, 32.5), np.full(10, 1.5)], 1)
            meas = cam + np.r_[rng.normal(0, 1.0, 2), 0.0]
            d = SIGN - cam
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            lat, lon, h = frame.to_geodetic(meas)
            obs = ray_observations(lat, lon, h, d, np.arange(10), np.arange(10) + 1000 * p, CLS)
        link(svc.matching, obs, [a if p < 6 else b] * len(obs), "veh-1", p, time.time())
    refresh(svc.matching, [a.id, b.id])
    f = facings_of(svc.matching, [a, b])
    assert f.known.all()
    apart = np.degrees(angle_between(f.azimuth[0], f.azimuth[1]))
    assert 60.0 + 3 * np.degrees(np.hypot(*f.sigma)) < apart < 140.0
    e = (b.x - a.x) @ frame.rotation.T
    assert 1.0 < np.hypot(e[0], e[1]) < 3.0
    config = svc.matching.config
    facing = dataclasses.replace(config.gate.facing, same_place_m=1.0)
    svc.matching.config = dataclasses.replace(
        config, gate=dataclasses.replace(config.gate, facing=facing)
    )
    assert merge_partner(svc.matching, a) is None and merge_partner(svc.matching, b) is None
    svc.matching.config = dataclasses.replace(config, merge_min_view_cos=-1.0)
    assert merge_partner(svc.matching, a) is b
    svc.matching.config = config  # the default: one place, one sign
    merge_touched(svc.matching, [a.id, b.id])
    assert len(svc.state.landmarks) == 1


def test_the_merged_landmarks_row_is_dropped_and_the_map_is_the_same(tmp_path: Path) -> None:
    """After a merge the matcher's sums hold a dead row; dropped at the next save
    (``compact_min_rows`` 1) or kept (the default), later rays give the same bits."""
    blobs = []
    for min_rows, dropped in ((1, 1), (1024, 0)):
        svc = matcher(tmp_path / f"m{min_rows}")
        svc.matching.config = dataclasses.replace(svc.config, compact_min_rows=min_rows)
        a, b = two_copies(svc)
        merge_touched(svc.matching, [b.id])
        with svc.transaction([svc]):
            svc.state.save(svc.sums.pack_rows)
        assert svc.matching.compact_rows() == dropped
        assert len(svc.sums) == 2 - dropped and a.row == (0 if dropped else a.row)
        frame = svc.frames(tile_of(svc.opts.zoom))
        rng = np.random.default_rng(11)
        for p in range(12, 16):
            link(svc.matching, sign_rays(frame, p, rng), [a] * 10, "veh-2", p, time.time())
        svc.sums.close_passes(clusters=svc.sums.open_clusters(a.row)[:3])
        refresh(svc.matching, [a.id])
        blobs.append((svc.sums.pack_rows([a.row])[0], a.x.tobytes(), a.cov.tobytes()))
        svc.db.close()
    assert blobs[0] == blobs[1]
