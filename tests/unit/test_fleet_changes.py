"""fleetsim.changes: scheduled changes to the signs, and the fleet driving against them."""

from __future__ import annotations

import json
from dataclasses import fields

import numpy as np
import pytest

from fleetsim.changes import KINDS, PLACEMENT, Change, ChangeSchedule, random_schedule
from fleetsim.fleet import Fleet, FleetConfig, Pass
from fleetsim.noise import FLEET
from fleetsim.world import Signs, demo_town, straight_road
from hdmap.geo.signs import CATALOG
from vehicle.config import load_vehicle_model

MODEL = load_vehicle_model()
ROAD = straight_road()  # one northbound road, sign 0 at y = 0: every pass sees it
TOWN = demo_town(3, n_signs=16, n_blocks=2)
CFG = FleetConfig(n_vehicles=2, start_time=1000.0, pass_interval_s=60.0)
N_PASSES = 6  # starts 1000, 1060, ..., 1300
T_CHANGE = 1150.0  # between the 3rd and 4th pass


def _ids(p: Pass, sign_id: int) -> np.ndarray:
    """Rows of the pass's detections of sign ``sign_id``."""
    return np.flatnonzero(p.truth.sign_id == sign_id)


def _passes(schedule: ChangeSchedule | None) -> list[Pass]:
    return list(Fleet(ROAD, MODEL, FLEET, CFG, seed=4, schedule=schedule).passes(N_PASSES))


def _before_after(passes: list[Pass], t: float = T_CHANGE) -> tuple[list[Pass], list[Pass]]:
    return [p for p in passes if p.start_time < t], [p for p in passes if p.start_time >= t]


def _at_y(sign: Signs, y: float) -> Signs:
    pos = sign.position.copy()
    pos[:, 1] = y
    return Signs(sign.id, sign.sign_class, pos, sign.facing, sign.panel_height_m)


def _assert_same_pass(a: Pass, b: Pass) -> None:
    assert (a.route, a.speed_mps, a.start_time) == (b.route, b.speed_mps, b.start_time)
    for group in ("fixes", "detections", "truth"):
        x, y = getattr(a, group), getattr(b, group)
        for f in fields(x):
            u, v = getattr(x, f.name), getattr(y, f.name)
            if isinstance(u, np.ndarray):
                np.testing.assert_array_equal(u, v, err_msg=f"{group}.{f.name}")
    np.testing.assert_array_equal(a.truth.gnss.total_enu, b.truth.gnss.total_enu)


# --- the fleet: no schedule changes nothing -----------------------------------------------


def test_no_schedule_and_empty_schedule_drive_the_same_passes_bit_for_bit() -> None:
    later = ChangeSchedule().with_removal(TOWN.signs, 3, 1e12)  # in effect after every pass
    fleets = [
        Fleet(TOWN, MODEL, FLEET, CFG, seed=7),
        Fleet(TOWN, MODEL, FLEET, CFG, seed=7, schedule=None),
        Fleet(TOWN, MODEL, FLEET, CFG, seed=7, schedule=ChangeSchedule()),
        Fleet(TOWN, MODEL, FLEET, CFG, seed=7, schedule=later),
    ]
    for v, k in ((0, 0), (1, 0), (0, 3), (1, 5)):
        base = fleets[0].drive(v, k)
        assert base.detections.image.size > 0
        for f in fleets[1:]:
            assert f.world_at(f.start_time(v, k)) is TOWN
            _assert_same_pass(base, f.drive(v, k))


# --- each kind of change, seen by the passes ------------------------------------------------


def test_removed_sign_is_seen_before_its_removal_and_never_after() -> None:
    before, after = _before_after(_passes(ChangeSchedule().with_removal(ROAD.signs, 0, T_CHANGE)))
    assert before and after
    assert all(_ids(p, 0).size for p in before)
    assert not any(_ids(p, 0).size for p in after)
    assert all((p.truth.sign_id == -1).all() for p in after)  # only false positives left


def test_moved_sign_is_seen_at_its_old_place_before_and_at_its_new_place_after() -> None:
    s = ChangeSchedule().with_move(ROAD.signs, 0, T_CHANGE, [0.0, 15.0])
    new_id = s.changes[0].new_id
    assert new_id == 1 and s.changes[0].events()[0].gone == (0,)
    old_pos, new_pos = ROAD.signs.position[0], ROAD.signs.position[0] + [0.0, 15.0, 0.0]
    np.testing.assert_array_equal(s.new_signs.position[0], new_pos)
    before, after = _before_after(_passes(s))
    for group, sign_id, pos, other in ((before, 0, old_pos, new_id), (after, new_id, new_pos, 0)):
        for p in group:
            rows = _ids(p, sign_id)
            assert rows.size and not _ids(p, other).size
            cam = p.truth.camera_enu[p.detections.image[rows]]
            np.testing.assert_allclose(p.truth.distance_m[rows], np.linalg.norm(cam - pos, axis=1))


def test_replaced_sign_is_detected_with_its_new_class_after() -> None:
    stop = CATALOG.code("stop")
    s = ChangeSchedule().with_replacement(ROAD.signs, 0, T_CHANGE, stop)
    assert s.new_signs.panel_height_m[0] == CATALOG.heights(np.array([stop]))[0]
    np.testing.assert_array_equal(s.new_signs.position, ROAD.signs.position)
    before, after = _before_after(_passes(s))
    for group, sign_id, cls in ((before, 0, ROAD.signs.sign_class[0]), (after, 1, stop)):
        for p in group:
            rows = _ids(p, sign_id)
            assert rows.size and (p.detections.sign_class[rows] == cls).all()
            assert not _ids(p, 1 - sign_id).size


def test_added_sign_appears_only_after_its_time_and_temporary_only_in_its_window() -> None:
    new = Signs.build([CATALOG.code("give_way")], [[6.5, 25.0, 2.3]], [180.0])
    s = ChangeSchedule().with_addition(ROAD.signs, T_CHANGE, new)
    s = s.with_addition(ROAD.signs, 1050.0, _at_y(new, -25.0), t_end=1250.0)
    added, temporary = s.changes[0].new_id, s.changes[1].new_id
    assert (added, temporary) == (1, 2)
    assert s.changes[1].events()[1].gone == (temporary,)
    passes = _passes(s)
    for p in passes:
        assert _ids(p, 0).size  # the old sign stays
        assert bool(_ids(p, added).size) == (p.start_time >= T_CHANGE)
        assert bool(_ids(p, temporary).size) == (1050.0 <= p.start_time < 1250.0)
    assert any(1050.0 <= p.start_time < 1250.0 for p in passes)


# --- the schedule itself ----------------------------------------------------------------


def test_ids_are_never_reused_and_bad_schedules_are_refused() -> None:
    s = random_schedule(TOWN, np.random.default_rng(0), 0.0, 100.0, 2, 2, 2, 2, 2)
    added = next(c for c in s.changes if c.kind == "add")
    s = s.with_removal(TOWN.signs, added.new_id, added.t + 1.0)  # a new sign taken down
    every, up, down = s.lifetimes(TOWN.signs)
    # 2 moved, 2 replaced, 4 put up: each its own id
    assert np.unique(every.id).size == len(every) == len(TOWN.signs) + 8
    assert not np.isin(s.new_signs.id, TOWN.signs.id).any()
    assert (up < down).all()
    for t in np.linspace(-1.0, 101.0, 30):
        standing = s.signs_at(TOWN.signs, float(t))
        assert np.unique(standing.id).size == len(standing)
    one = ChangeSchedule().with_removal(TOWN.signs, 0, 5.0)
    with pytest.raises(ValueError, match="taken down once"):
        one.with_removal(TOWN.signs, 0, 6.0)
    moved = ChangeSchedule().with_move(TOWN.signs, 1, 5.0, [0.0, 9.0])  # puts up sign 16
    with pytest.raises(ValueError, match="after it is put up"):
        moved.with_removal(TOWN.signs, 16, 4.0)
    temp = ChangeSchedule().with_addition(TOWN.signs, 1.0, TOWN.signs.take([0]), t_end=2.0)
    with pytest.raises(ValueError, match="if not temporary"):
        temp.with_removal(TOWN.signs, 16, 1.5)
    with pytest.raises(ValueError, match="must not be the world's"):
        ChangeSchedule().with_move(ROAD.signs, 0, 1.0, [0, 9]).check(TOWN.signs)
    with pytest.raises(ValueError, match="no sign 99"):
        ChangeSchedule().with_removal(TOWN.signs, 99, 1.0)
    with pytest.raises(ValueError, match="not a valid change"):
        Change("temporary", 5.0, new_id=3, t_end=4.0)


def test_schedule_json_round_trips_and_describes_each_change() -> None:
    s = random_schedule(TOWN, np.random.default_rng(1), 0.0, 500.0, 1, 1, 1, 1, 1)
    back = ChangeSchedule.from_json(json.loads(json.dumps(s.to_json())))
    assert back.changes == s.changes
    for f in fields(Signs):
        np.testing.assert_array_equal(getattr(back.new_signs, f.name), getattr(s.new_signs, f.name))
    for t in (0.0, 250.0, 500.0):
        a, b = s.signs_at(TOWN.signs, t), back.signs_at(TOWN.signs, t)
        np.testing.assert_array_equal(a.id, b.id)
        np.testing.assert_array_equal(a.position, b.position)
    report = json.loads(json.dumps(s.describe(TOWN.signs)))
    assert sorted(d["kind"] for d in report) == sorted(KINDS)
    for d in report:
        assert (d["old"] is None) == (d["old_id"] < 0) and (d["new"] is None) == (d["new_id"] < 0)
        assert (d["moved_m"] is None) == (d["kind"] not in ("move", "replace"))
        assert len(d["events"]) == (2 if d["kind"] == "temporary" else 1)
    assert ChangeSchedule.from_json(ChangeSchedule().to_json()).changes == ()


def test_random_schedule_is_deterministic_and_places_signs_beside_the_roads() -> None:
    def draw(seed: int) -> ChangeSchedule:
        return random_schedule(TOWN, np.random.default_rng(seed), 10.0, 90.0, 2, 4, 2, 2, 2)

    s = draw(5)
    assert s.to_json() == draw(5).to_json() != draw(6).to_json()
    assert [c.t for c in s.changes] == sorted(c.t for c in s.changes)
    assert all(10.0 <= c.t <= (c.t_end or c.t) <= 90.0 for c in s.changes)
    old = [c.old_id for c in s.changes if c.old_id >= 0]
    assert len(set(old)) == len(old) == 8 and np.isin(old, TOWN.signs.id).all()
    every = s.lifetimes(TOWN.signs)[0]
    rows = {c.kind: [] for c in s.changes}
    for c in s.changes:
        rows[c.kind].append((every.index_of([c.old_id])[0], every.index_of([c.new_id])[0]))
    for i, j in rows["move"]:
        assert 5.0 <= np.linalg.norm(every.position[j, :2] - every.position[i, :2]) <= 30.0
        assert every.sign_class[i] == every.sign_class[j]
        assert every.position[i, 2] == every.position[j, 2]
    for i, j in rows["replace"]:
        assert every.sign_class[i] != every.sign_class[j]
        assert every.sign_class[j] in TOWN.signs.sign_class
        np.testing.assert_array_equal(every.position[i], every.position[j])
    # Moved and put-up signs stand as the town's own: facing the traffic of a street
    # (within 8 deg of its axis), 2.5-4 m right of its lane centre, 2-2.8 m high.
    placed = [j for kind in ("move", "add", "temporary") for _, j in rows[kind]]
    assert len(placed) == 8
    az = every.facing_azimuth_deg[placed]
    assert (np.abs((az + 45.0) % 90.0 - 45.0) <= PLACEMENT.facing_jitter_deg + 1e-9).all()
    north_south = np.abs((az + 45.0) % 180.0 - 45.0) < 45.0  # facing North or South
    across = np.where(north_south, every.position[placed, 0], every.position[placed, 1])
    grid = np.unique(TOWN.nodes[:, 0])  # the streets' x (and y: a square grid)
    off = np.min(np.abs(across[:, None] - grid[None, :]), axis=1)
    lane = TOWN.lane_offset_m
    assert ((off >= lane + 2.5 - 1e-9) & (off <= lane + 4.0 + 1e-9)).all()
    assert ((every.position[placed, 2] >= 2.0) & (every.position[placed, 2] <= 2.8)).all()


def test_town_fleet_sees_only_the_signs_standing_at_each_pass_start() -> None:
    cfg = FleetConfig(n_vehicles=3, start_time=0.0, pass_interval_s=10.0)
    s = random_schedule(TOWN, np.random.default_rng(2), 0.0, 240.0, 3, 3, 3, 3, 3)
    fleet = Fleet(TOWN, MODEL, FLEET, cfg, seed=1, schedule=s)
    every, up, down = s.lifetimes(TOWN.signs)
    seen_new = set()
    for p in fleet.passes(24):
        ids = np.unique(p.truth.sign_id[p.truth.sign_id >= 0])
        r = every.index_of(ids)
        assert ((up[r] <= p.start_time) & (p.start_time < down[r])).all()
        seen_new |= set(ids[np.isin(ids, s.new_signs.id)].tolist())
    assert len(seen_new) >= 3
