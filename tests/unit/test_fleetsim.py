"""fleetsim: world, routes, drive, noise statistics, fleet determinism, and the demo command."""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from fleetsim.drive import DriveParams, simulate_pass
from fleetsim.fleet import Fleet, FleetConfig, distinct_signs_seen, vehicle_id
from fleetsim.noise import EXACT, FLEET, PAPER, GnssNoise
from fleetsim.route import HEADING_RAMP_M, offset_right, random_route, speed_profile
from fleetsim.route import Path as RoutePath
from fleetsim.truth import lines_in_world, match_landmarks, ray_errors
from fleetsim.world import Signs, demo_town, straight_road, tile_border_distance
from hdmap.geo.geodesy import ecef_to_enu_vectors
from hdmap.geo.signs import CATALOG
from hdmap.geo.tiles import quadkeys_of, tiles_around
from vehicle.config import load_vehicle_model
from vehicle.geoloc import detection_reach, geolocate

MODEL = load_vehicle_model()
TOWN = demo_town(0)
W, H = MODEL.intrinsics.width, MODEL.intrinsics.height


def _unclipped(box: np.ndarray) -> np.ndarray:
    return (box[:, 0] > 0) & (box[:, 1] > 0) & (box[:, 2] < W - 1) & (box[:, 3] < H - 1)


# --- world ---------------------------------------------------------------------------


def test_demo_town_layout() -> None:
    s = TOWN.signs
    assert 35 <= len(s) <= 45
    assert np.unique(s.sign_class).size >= 8
    assert CATALOG.known(s.sign_class).all()
    assert np.unique(s.id).size == len(s)
    assert ((s.position[:, 2] >= 2.0) & (s.position[:, 2] <= 2.8)).all()
    np.testing.assert_allclose(s.panel_height_m, CATALOG.heights(s.sign_class))
    np.testing.assert_allclose(np.linalg.norm(s.facing, axis=1), 1.0)
    # Beside a street: 2.5-4 m right of the lane centre, i.e. of the centreline + lane offset.
    grid = np.unique(TOWN.nodes[:, 0])
    off = np.min(np.abs(s.position[:, :2, None] - grid[None, None, :]), axis=(1, 2))
    assert ((off >= TOWN.lane_offset_m + 2.5 - 1e-9) & (off <= TOWN.lane_offset_m + 4.0)).all()
    # Facing oncoming traffic: within 8 deg of a street axis.
    az = s.facing_azimuth_deg
    assert (np.abs((az + 45.0) % 90.0 - 45.0) <= 8.0 + 1e-9).all()


def test_demo_town_has_close_same_class_pairs_and_tile_border_signs() -> None:
    s = TOWN.signs
    d = np.linalg.norm(s.position[:, None, :2] - s.position[None, :, :2], axis=-1)
    same = (s.sign_class[:, None] == s.sign_class[None, :]) & ~np.eye(len(s), dtype=bool)
    pairs = np.argwhere(same & (d >= 3.0) & (d <= 10.0))
    assert len(pairs) // 2 >= 3
    border = tile_border_distance(TOWN, s.position[:, :2])
    assert (border < 15.0).sum() >= 3
    lat, lon, _ = TOWN.signs_geodetic()
    straddling = [len(tiles_around(la, lo, 15.0)) > 1 for la, lo in zip(lat, lon, strict=True)]
    assert sum(straddling) >= 3
    assert np.unique(quadkeys_of(lat, lon, 16)).size >= 2
    np.testing.assert_allclose(TOWN.frame.from_geodetic(lat, lon, _), s.position, atol=1e-6)


def test_demo_town_is_deterministic_per_seed() -> None:
    a, b, c = demo_town(5), demo_town(5), demo_town(6)
    np.testing.assert_array_equal(a.signs.position, b.signs.position)
    assert not np.array_equal(a.signs.position, c.signs.position)


def test_sign_index_of() -> None:
    s = TOWN.signs.take(np.array([3, 1, 2]))
    assert s.index_of(np.array([1, 2, 3, 99, -1])).tolist() == [1, 2, 0, -1, -1]


# --- routes --------------------------------------------------------------------------


def test_lane_offset_is_to_the_right_and_corners_are_round() -> None:
    pts = np.array([[0.0, 0.0], [0.0, 100.0], [100.0, 100.0]])  # north, then east
    lane = offset_right(pts, 1.75)
    np.testing.assert_allclose(lane, [[1.75, 0.0], [1.75, 98.25], [100.0, 98.25]])
    path = RoutePath.from_points(lane)
    _, psi = path.at(np.array([10.0, path.length - 10.0]))
    np.testing.assert_allclose(np.degrees(psi), [0.0, 90.0], atol=1e-9)
    smooth = RoutePath.along(TOWN, [0, 1, 6])
    _, psi = smooth.at(np.linspace(0.0, smooth.length, 400))
    assert np.max(np.abs(np.diff(np.degrees(psi)))) < 10.0  # no heading jump at the corner


def test_the_heading_is_the_direction_of_travel_away_from_the_corners() -> None:
    """Invariant of ``Path.heading_knots``: on a straight the heading is the straight's
    direction up to HEADING_RAMP_M from its ends (interpolating between segment middles
    turned it over the straight's last half: 3.9 deg off 10 m before this corner), and on a
    rounded corner the course of the positions (central differences at 0.2 s, 10 m/s)
    stays within a few degrees of it."""
    path = RoutePath.along(TOWN, [0, 1, 6])
    straight = np.diff(path.s) > 2.0 * HEADING_RAMP_M
    first = int(np.flatnonzero(straight)[0])
    a, b = path.s[first], path.s[first + 1]
    d = path.points[first + 1] - path.points[first]
    s = np.linspace(a + HEADING_RAMP_M, b - HEADING_RAMP_M, 200)
    _, psi = path.at(s)
    np.testing.assert_allclose(psi, np.arctan2(d[0], d[1]), atol=1e-12)
    t = np.arange(0.0, path.length / 10.0, 0.2)
    xy, psi = path.at(10.0 * t)
    v = np.gradient(xy, t, axis=0)
    moving = (10.0 * t > 1.0) & (10.0 * t < path.length - 1.0)
    off = np.degrees(np.angle(np.exp(1j * (np.arctan2(v[:, 0], v[:, 1]) - psi))))[moving]
    assert np.sqrt(np.mean(off**2)) < 1.0 and np.max(np.abs(off)) < 6.0, off


def test_the_driver_slows_for_corners_within_the_lateral_limit() -> None:
    """On the demo town's corner (7 m radius) the speed profile keeps ``v^2 kappa`` within
    the lateral limit over the curvature window, brakes and speeds up at the longitudinal
    limit, and cruises at ``v_max`` on the straights; without a limit the speed is
    constant."""
    path = RoutePath.along(TOWN, [0, 1, 6])
    prof = speed_profile(path, 11.0, 3.0)
    v = np.diff(prof.s) / np.diff(prof.t)
    assert np.all(np.diff(prof.t) > 0) and v.max() == pytest.approx(11.0, abs=1e-9)
    assert 3.0 < v.min() < 6.0  # sqrt(3 m/s^2 * 7 m) = 4.6 m/s round the corner
    a = np.diff(v) / np.diff(prof.t)[1:]
    assert np.max(np.abs(a)) <= 2.0 * 1.05
    psi = np.interp(prof.s, *path.heading_knots())
    yaw = np.abs(np.diff(psi)) / np.diff(prof.t)
    assert yaw.max() < 1.2  # rad/s; at 11 m/s round 7 m it was 1.6
    const = speed_profile(path, 11.0, None)
    assert const.duration == pytest.approx(path.length / 11.0)
    assert prof.duration > const.duration
    with pytest.raises(ValueError, match="lateral_accel_mps2"):
        DriveParams(lateral_accel_mps2=0.0)


def test_random_routes_have_no_u_turns() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        r = random_route(TOWN, rng, 500.0)
        assert all(r[i] != r[i + 2] for i in range(len(r) - 2))
        e = {tuple(x) for x in TOWN.edges.tolist()}
        assert all((a, b) in e for a, b in itertools.pairwise(r))
    assert random_route(straight_road(), rng, 1e4) == [0, 1]


# --- drive geometry ------------------------------------------------------------------


def test_zero_noise_rays_pass_through_the_true_sign_centre() -> None:
    """Ties the simulator's projection to vehicle.geoloc's inverse (a fix at every frame:
    no interpolation; for that see the next test and tests/unit/test_geoloc.py)."""
    fleet = Fleet(TOWN, MODEL, EXACT, FleetConfig(n_vehicles=3, fix_per_frame=True), seed=1)
    misses, rel_range, n_clipped = [], [], 0
    for p in fleet.passes(9):
        assert (p.truth.sign_id >= 0).all()
        lines = geolocate(p.fixes, p.detections, MODEL)
        err = ray_errors(lines, p.truth.sign_id, TOWN)
        whole = _unclipped(p.detections.box[err.rows])
        n_clipped += int((~whole).sum())
        misses.append(err.miss_m[whole])
        ok = np.isfinite(err.range_error_m)
        rel_range.append(np.abs(err.range_error_m[ok]) / err.true_range_m[ok])
        # The true distance the simulator reports is the one geolocate should find.
        np.testing.assert_allclose(p.truth.distance_m[err.rows], err.true_range_m, atol=0.01)
    miss, rel = np.concatenate(misses), np.concatenate(rel_range)
    assert miss.size > 300 and rel.size > 300
    assert miss.max() < 0.01
    assert rel.max() < 0.01
    assert n_clipped > 0  # boxes cut by the border exist (and carry no range)


@pytest.mark.parametrize(
    "params",
    [DriveParams(), DriveParams(frame_rate_hz=30.0, gnss_rate_hz=1.0, gnss_miss_prob=0.1)],
    ids=["default", "1hz-gnss-30hz-camera"],
)
def test_zero_noise_straight_road_is_exact(params: DriveParams) -> None:
    """The simulator's own timing (fixes with jitter and misses, frames on their own clock):
    interpolated poses on a straight road at constant speed are exact."""
    world = straight_road(5.0, 2.4)
    rng = np.random.default_rng(0)
    path = RoutePath.along(world, [0, 1])
    fixes, det, truth = simulate_pass(world, path, MODEL, EXACT, rng, params=params)
    assert det.t is not None and not np.isin(fixes.t, truth.t).any()
    assert np.unique(np.round(np.diff(fixes.t) * params.gnss_rate_hz, 2)).size > 2  # jitter
    np.testing.assert_array_equal(det.t, truth.t[det.image])
    reach = detection_reach(fixes, det)
    assert reach.mean() > 0.9
    det, sign_id = det.take(np.flatnonzero(reach)), truth.sign_id[reach]
    lines = geolocate(fixes, det, MODEL)
    err = ray_errors(lines, sign_id, world)
    assert len(det) > 15 * params.frame_rate_hz / 5.0
    whole = _unclipped(det.box)
    # Sub-mm: only the Earth's curvature (level vehicle in the local, not the world, frame).
    assert err.miss_m[whole].max() < 1e-3
    # a box cut by the image border moves its centre by at most half the panel
    assert (err.miss_m[~whole] < world.signs.panel_height_m[0] / 2.0).all()
    dist = world.signs.position[0, 1] - truth.camera_enu[det.image, 1]
    assert dist.max() < 60.0 and dist.min() > 5.0  # from max range until it leaves the image
    origin, _ = lines_in_world(lines, world)
    np.testing.assert_allclose(origin, truth.camera_enu[det.image], atol=1e-3)


def test_visibility_rules() -> None:
    world = straight_road(5.0, 2.4)
    path = RoutePath.along(world, [0, 1])

    def n_det(w, **kw) -> int:
        params = DriveParams(**kw)
        rng = np.random.default_rng(0)
        return len(simulate_pass(w, path, MODEL, EXACT, rng, params=params)[1])

    base = n_det(world)
    s = world.signs
    turned = Signs(s.id, s.sign_class, s.position, -s.facing, s.panel_height_m)
    assert n_det(world.with_signs(turned)) == 0  # facing away
    side = Signs(s.id, s.sign_class, s.position, np.array([[-1.0, 0.0, 0.0]]), s.panel_height_m)
    assert n_det(world.with_signs(side)) < base / 2  # seen edge-on: only close by, obliquely
    assert 0 < n_det(world, max_range_m=30.0) < base
    assert n_det(world, min_box_px=40.0) < base
    from dataclasses import replace

    wall = replace(world, buildings=np.array([[4.0, -80.0, 20.0, -10.0]]))
    assert n_det(wall) < base  # hidden by a building until past it


def test_boxes_stay_inside_the_image() -> None:
    for p in Fleet(TOWN, MODEL, FLEET, seed=2).passes(10):
        b = p.detections.box
        assert ((b[:, 0] >= 0) & (b[:, 2] <= W - 1) & (b[:, 1] >= 0) & (b[:, 3] <= H - 1)).all()
        assert ((b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])).all()
        assert np.all(np.diff(p.detections.image) >= 0)
        assert len(p.truth.sign_id) == len(p.detections)


# --- noise statistics ----------------------------------------------------------------


def _gnss_errors(p) -> tuple[np.ndarray, np.ndarray]:
    """Observed antenna position errors (ENU m) and heading errors (rad) of a pass."""
    e = TOWN.frame.from_geodetic(p.fixes.lat, p.fixes.lon, p.fixes.h) - p.truth.antenna_enu
    psi = p.truth.fix_heading_rad
    fwd = np.column_stack([np.sin(psi), np.cos(psi), np.zeros_like(psi)])
    local = ecef_to_enu_vectors(TOWN.frame.vectors_to_ecef(fwd), p.fixes.lat, p.fixes.lon)
    true_deg = np.degrees(np.arctan2(local[:, 0], local[:, 1]))
    dh = np.radians((p.fixes.heading_deg - true_deg + 180.0) % 360.0 - 180.0)
    return e, dh


@pytest.fixture(scope="module")
def fleet_passes() -> list:
    cfg = FleetConfig(n_vehicles=5, route_length_m=(300.0, 500.0))
    return list(Fleet(TOWN, MODEL, FLEET, cfg, seed=11).passes(300))


def test_fleet_gnss_statistics(fleet_passes) -> None:
    start_bias, diffs, dts, heading_bias, heading_white = [], [], [], [], []
    n_jump = n_fix = 0
    for p in fleet_passes:
        e, dh = _gnss_errors(p)
        jump = np.hypot(*(e - np.median(e, axis=0))[:, :2].T) > 12.0
        n_jump += int(jump.sum())
        n_fix += len(e)
        np.testing.assert_array_equal(jump, p.truth.gnss.multipath)
        early = (p.fixes.t - p.fixes.t[0] < 5.0) & ~jump
        start_bias.append(e[early].mean(axis=0))
        ok = ~jump[1:] & ~jump[:-1]
        diffs.append(np.diff(e, axis=0)[ok])
        dts.append(np.diff(p.fixes.t)[ok])
        heading_bias.append(dh.mean())
        heading_white.append(dh - dh.mean())
    bias_std = np.std(start_bias, axis=0)
    assert 2.2 < bias_std[0] < 2.8 and 2.2 < bias_std[1] < 2.8  # per-pass bias 2.5 m
    assert 3.0 < bias_std[2] < 4.0  # vertical 3.5 m
    # Successive differences: var = 2 white^2 + walk^2 E[dt] (dt about 0.2 s; misses: 0.4).
    d, dt = np.concatenate(diffs), np.concatenate(dts)
    white = np.sqrt((d.var(axis=0) - np.array([0.2**2, 0.2**2, 0.3**2]) * dt.mean()) / 2.0)
    np.testing.assert_allclose(white, [1.0, 1.0, 1.5], rtol=0.05)
    assert 0.025 < n_jump / n_fix < 0.035  # multipath 3%
    assert 0.017 < np.std(heading_bias) < 0.023  # heading bias 0.02 rad
    assert 0.009 < np.concatenate(heading_white).std() < 0.011  # heading white 0.01 rad
    p = fleet_passes[0]
    assert (p.fixes.sigma_h_m == 1.0).all() and (p.fixes.sigma_v_m == 1.5).all()
    assert p.fixes.sigma_heading_deg[0] == pytest.approx(np.degrees(0.01), abs=1e-3)


def test_fleet_detector_statistics(fleet_passes) -> None:
    n_true = n_visible = n_fp_images = n_images = 0
    px = []
    for p in fleet_passes:
        tr = p.truth.sign_id >= 0
        n_true += int(tr.sum())
        n_visible += len(p.truth.visible_image)
        n_fp_images += np.unique(p.detections.image[~tr]).size
        n_images += len(p.truth.t)  # every camera frame, with detections or not
        b = p.detections.box[tr]
        centre = np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2])
        px.append((centre - p.truth.uv_true[tr])[_unclipped(b)])
        assert np.isnan(p.truth.uv_true[~tr]).all()
    assert 0.78 < n_true / n_visible < 0.82  # detection probability 0.8
    assert 0.017 < n_fp_images / n_images < 0.023  # a false positive in 2% of images
    np.testing.assert_allclose(np.concatenate(px).std(axis=0), [3.0, 3.0], rtol=0.05)


def test_box_size_noise_moves_the_edges_and_keeps_the_rest_of_the_stream() -> None:
    from dataclasses import replace

    sized = replace(FLEET, detector=replace(FLEET.detector, size_sigma_px=4.0))
    with pytest.raises(ValueError, match="size_sigma_px"):
        replace(FLEET.detector, size_sigma_px=-1.0)
    dh, dw = [], []
    for k in range(4):
        a = Fleet(TOWN, MODEL, FLEET, seed=5).drive(0, k)
        b = Fleet(TOWN, MODEL, sized, seed=5).drive(0, k)
        # the size noise is drawn last: the same detections, centres, fixes and truth (in
        # a frame's order by the noisy box's left edge: compare by frame and sign)
        oa = np.lexsort((a.truth.sign_id, a.detections.image))
        ob = np.lexsort((b.truth.sign_id, b.detections.image))
        np.testing.assert_array_equal(a.detections.image[oa], b.detections.image[ob])
        np.testing.assert_array_equal(a.truth.sign_id[oa], b.truth.sign_id[ob])
        np.testing.assert_array_equal(a.fixes.lat, b.fixes.lat)
        ba, bb = a.detections.box[oa], b.detections.box[ob]
        ok = _unclipped(ba) & _unclipped(bb) & (a.truth.sign_id[oa] >= 0)
        np.testing.assert_allclose((ba[ok, 1] + ba[ok, 3]) / 2, (bb[ok, 1] + bb[ok, 3]) / 2)
        np.testing.assert_allclose((ba[ok, 0] + ba[ok, 2]) / 2, (bb[ok, 0] + bb[ok, 2]) / 2)
        dh.append((bb[ok, 3] - bb[ok, 1]) - (ba[ok, 3] - ba[ok, 1]))
        dw.append((bb[ok, 2] - bb[ok, 0]) - (ba[ok, 2] - ba[ok, 0]))
    dh, dw = np.concatenate(dh), np.concatenate(dw)
    assert dh.size > 200
    assert abs(dh.mean()) < 0.5 and 3.6 < dh.std() < 4.4  # 4 px on the height
    assert 3.6 < dw.std() < 4.4 and abs(np.corrcoef(dh, dw)[0, 1]) < 0.15


def test_paper_preset_is_white_only() -> None:
    world = straight_road(5.0, 2.4)
    errs, heads, px, n_vis, n_det = [], [], [], 0, 0
    for p in Fleet(world, MODEL, PAPER, FleetConfig(n_vehicles=4), seed=3).passes(60):
        e, dh = _gnss_errors(p)
        errs.append(e)
        heads.append(dh)
        n_vis += len(p.truth.visible_image)
        n_det += len(p.detections)
        assert (p.truth.sign_id >= 0).all()
        b = p.detections.box
        centre = np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2])
        px.append((centre - p.truth.uv_true)[_unclipped(b)])
        assert not p.truth.gnss.multipath.any()
    e = np.concatenate(errs)
    np.testing.assert_allclose(e[:, :2].std(axis=0), [5.0, 5.0], rtol=0.05)
    assert np.abs(e[:, 2]).max() < 1e-6  # 2D: no vertical noise
    assert np.abs(np.mean([x.mean(axis=0) for x in errs], axis=0)[:2]).max() < 0.5  # no bias
    assert np.concatenate(heads).std() == pytest.approx(0.35, rel=0.05)
    assert n_det == n_vis
    np.testing.assert_allclose(np.concatenate(px).std(axis=0), [5.0, 5.0], rtol=0.1)
    assert PAPER.gnss.reported_sigmas() == (5.0, 1.0, 20.054)


def test_reported_sigmas_are_configurable() -> None:
    g = GnssNoise(white_h_m=1.0, white_v_m=1.5, reported_sigma_h_m=3.0)
    assert g.reported_sigmas() == (3.0, 1.5, 0.001)
    with pytest.raises(ValueError, match="multipath_prob"):
        GnssNoise(multipath_prob=1.5)


# --- fleet ---------------------------------------------------------------------------


def test_fleet_is_deterministic_per_vehicle_and_pass() -> None:
    a = Fleet(TOWN, MODEL, FLEET, seed=3)
    b = Fleet(TOWN, MODEL, FLEET, seed=3)
    c = Fleet(TOWN, MODEL, FLEET, seed=4)
    p, q, r = a.drive(1, 2), b.drive(1, 2), c.drive(1, 2)
    np.testing.assert_array_equal(p.fixes.lat, q.fixes.lat)
    np.testing.assert_array_equal(p.detections.box, q.detections.box)
    np.testing.assert_array_equal(p.truth.sign_id, q.truth.sign_id)
    assert p.route == q.route and p.speed_mps == q.speed_mps
    assert not (p.route == r.route and np.array_equal(p.fixes.lat, r.fixes.lat))
    ordered = list(a.passes(25))
    assert ordered[10 * 2 + 1].fixes.lat.tolist() == p.fixes.lat.tolist()
    assert [x.start_time for x in ordered] == sorted(x.start_time for x in ordered)
    assert ordered[0].vehicle_id == vehicle_id(0) == "veh-0001"
    assert {x.vehicle_id for x in ordered} == set(a.vehicle_ids)
    assert all(8.0 <= x.speed_mps <= 14.0 for x in ordered)
    first = ordered[0]
    np.testing.assert_allclose(np.diff(first.truth.t), 0.2, atol=1e-6)  # camera: 5 Hz
    slots = np.diff(first.fixes.t) / 0.2  # GNSS: 5 Hz slots, jittered, a few missing
    assert np.allclose(slots, np.round(slots), atol=0.35) and (np.round(slots) >= 1).all()
    assert 0.85 < len(first.fixes) / (first.truth.t[-1] - first.truth.t[0]) / 5.0 < 1.05


def test_match_landmarks_pairs_by_class_and_distance() -> None:
    s = TOWN.signs
    pos = s.position.copy()
    pos[:, 0] += 1.0
    lat, lon, h = TOWN.frame.to_geodetic(pos[:-1])
    cls = s.sign_class[:-1].copy()
    cls[0] = 99  # wrong class: unmatched
    m = match_landmarks(TOWN, lat, lon, h, cls, gate_m=5.0)
    assert m.landmark.size == len(s) - 2
    np.testing.assert_allclose(m.error_enu[:, 0], 1.0, atol=1e-6)
    assert m.spurious.tolist() == [0]
    assert sorted(m.missed.tolist()) == [0, len(s) - 1]


# --- the demo command ----------------------------------------------------------------


def test_match_prefers_a_confirmed_landmark_to_a_nearer_candidate() -> None:
    """Sign 0 has a confirmed landmark 1.0 m off and a candidate 0.5 m off: the confirmed
    one is its pair, the candidate is the unpaired one (by distance alone it was the other
    way round, and the confirmed landmark counted as a duplicate)."""
    s = TOWN.signs
    pos = np.stack([s.position[0] + [1.0, 0, 0], s.position[0] + [0.5, 0, 0]])
    lat, lon, h = TOWN.frame.to_geodetic(pos)
    cls = np.full(2, s.sign_class[0])
    by_distance = match_landmarks(TOWN, lat, lon, h, cls, gate_m=5.0)
    assert by_distance.landmark.tolist() == [1]
    m = match_landmarks(TOWN, lat, lon, h, cls, gate_m=5.0, preferred=[True, False])
    assert m.landmark.tolist() == [0] and m.spurious.tolist() == [1]
    np.testing.assert_allclose(m.error_enu[0, 0], 1.0, atol=1e-6)
    # a candidate still pairs where no confirmed landmark of the sign is in reach
    m = match_landmarks(TOWN, lat[1:], lon[1:], h[1:], cls[1:], gate_m=5.0, preferred=[False])
    assert m.landmark.tolist() == [0]


def test_demo_command_writes_png_and_json(tmp_path: Path, capsys) -> None:
    from hdmap.cli import vehicle_demo as demo

    args = argparse.Namespace(
        out=tmp_path / "out", seed=0, town_seed=0, vehicle_config=None, max_rows=5
    )
    assert demo.run(args) == 0
    png = (tmp_path / "out" / "vehicle_rays.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    doc = json.loads((tmp_path / "out" / "vehicle_rays.json").read_text())
    assert len(doc["rays"]) > 10 and len(doc["signs"]) == len(TOWN.signs)
    seen = {r["true_sign_id"] for r in doc["rays"]} - {-1}
    assert len(seen) >= 3
    assert {"azimuth_deg", "elevation_deg", "sigma_az_deg", "range_m", "lat", "lon"} <= set(
        doc["rays"][0]
    )
    out = capsys.readouterr().out
    assert "az[deg]" in out and "wrote" in out


def test_demo_command_rejects_a_bad_vehicle_config(tmp_path: Path, capsys) -> None:
    from hdmap.cli import vehicle_demo as demo

    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nfx = -1\n")
    args = argparse.Namespace(out=tmp_path, seed=0, town_seed=0, vehicle_config=bad, max_rows=5)
    assert demo.run(args) == 2
    assert "camera.fx" in capsys.readouterr().err


def test_distinct_signs_seen() -> None:
    p = Fleet(TOWN, MODEL, EXACT, seed=0).drive(0, 0)
    assert distinct_signs_seen(p) == np.unique(p.truth.sign_id).size


# --- the vehicle's fix check against simulated multipath ------------------------------


@pytest.mark.parametrize("noise", [FLEET, PAPER], ids=["fleet", "paper"])
def test_fix_check_finds_the_multipath_jumps_and_little_else(noise) -> None:
    from vehicle.geoloc import fix_outliers

    fleet = Fleet(TOWN, MODEL, noise, seed=4)
    flagged, jumps, n = 0, 0, 0
    hit = 0
    for k in range(30):
        p = fleet.drive(k % 5, k)
        bad = fix_outliers(p.fixes)
        mp = p.truth.gnss.multipath
        n += mp.size
        jumps += int(mp.sum())
        hit += int((bad & mp).sum())
        flagged += int((bad & ~mp).sum())
    assert n > 3000
    if noise is FLEET:  # 3 % of fixes jump 20-50 m
        assert jumps > 0.02 * n and hit >= 0.97 * jumps, (hit, jumps)
    else:
        assert jumps == 0
    assert flagged <= 0.002 * n, (flagged, n)


def test_real_panel_sizes_are_per_sign_reproducible_and_spread_as_claimed():
    """``Signs.with_real_sizes``: each panel's log size ratio ~ N(0, rel); the sample
    variance of n = 2,000 signs within its chi-square 99.9 % interval; a sign keeps its
    size when the others change."""
    from scipy.stats import chi2

    from fleetsim.world import Signs

    n, rel = 2000, 0.1
    signs = Signs.build(np.full(n, 1), np.zeros((n, 3)), np.zeros(n))
    real = signs.with_real_sizes(rel, seed=3)
    z = np.log(real.panel_height_m / signs.panel_height_m) / rel
    lo, hi = chi2.ppf([0.0005, 0.9995], n - 1) / (n - 1)
    assert lo <= np.var(z, ddof=1) <= hi
    assert abs(z.mean()) <= 3.3 / np.sqrt(n)
    again = signs.take(np.arange(10, 20)).with_real_sizes(rel, seed=3)
    np.testing.assert_array_equal(again.panel_height_m, real.panel_height_m[10:20])
    other = signs.with_real_sizes(rel, seed=4)
    assert not np.allclose(other.panel_height_m, real.panel_height_m)
