"""Scoring a map against a changing world (fleetsim/evaluation/changes_scoring.py) on hand
made maps: one northbound road, its sign at y = 0 (facing South); changes at t = 100.

A removal is reflected once no landmark of its class stands at its place; a move once a
landmark holds the new place and none the old; an addition needs a landmark that is not
doubtful, and is located once that landmark is confirmed. Passes count only when their
camera had the sign in view from the side it faces; a standing sign whose landmark
disappears is a false revocation.
"""

from __future__ import annotations

import numpy as np

from fleetsim.changes import ChangeSchedule
from fleetsim.evaluation.changes_scoring import ChangeScorer, calibration, summary
from fleetsim.world import straight_road
from schemas.map import MapLandmarks

WORLD = straight_road()
SIGN = WORLD.signs


def landmarks(rows: list[tuple[int, int, float, float, int, int]]) -> MapLandmarks:
    """(id, class, east, north, status, exist_state) -> a published table."""
    n = len(rows)
    e = np.array([r[2] for r in rows], float)
    nn = np.array([r[3] for r in rows], float)
    lat, lon, h = WORLD.frame.to_geodetic(np.column_stack([e, nn, np.full(n, 2.4)]))
    return MapLandmarks(
        id=np.array([r[0] for r in rows], np.uint64),
        sign_class=np.array([r[1] for r in rows], np.uint16),
        lat=np.atleast_1d(lat),
        lon=np.atleast_1d(lon),
        h=np.atleast_1d(h),
        cov=np.tile([0.1, 0, 0, 0.1, 0, 0.1], (n, 1)),
        status=np.array([r[4] for r in rows], np.uint8),
        n_obs=np.ones(n, np.uint32),
        n_passes=np.ones(n, np.uint32),
        revision=np.ones(n, np.uint64),
        updated_at=np.zeros(n),
        source_time=np.zeros(n),
        exist_state=np.array([r[5] for r in rows], np.uint8),
        p_exist=np.where(np.array([r[5] for r in rows]) == 2, 0.3, 0.99).astype(np.float32),
    )


CLS = int(SIGN.sign_class[0])
X0 = float(SIGN.position[0, 0])


def drive_north(scorer: ChangeScorer, t: float, back: bool = False) -> None:
    """One pass along the lane, northbound (or southbound: the sign's back)."""
    y = np.linspace(-100.0, 20.0, 121)
    if back:
        y = y[::-1]
    cam = np.column_stack([np.full(y.size, 1.75), y])
    scorer.note_pass(t, np.arange(y.size) * 0.1, cam, np.full(y.size, 180.0 if back else 0.0))


def test_a_removal_counts_passes_that_drove_by_until_no_landmark_stands_there():
    sch = ChangeSchedule().with_removal(SIGN, 0, 100.0)
    s = ChangeScorer(WORLD, sch)
    drive_north(s, 50.0)  # before the change: not counted
    drive_north(s, 150.0)
    drive_north(s, 160.0, back=True)  # the sign's back: not counted
    drive_north(s, 170.0)
    s.check(180.0, landmarks([(7, CLS, X0 + 0.5, 0.3, 1, 1)]))
    assert s.events[0].reflected_at is None and s.events[0].waiting_for == [7]
    drive_north(s, 190.0)
    s.check(200.0, landmarks([]))
    e = s.events[0]
    assert e.reflected_at == 200.0 and e.passes_to_reflect == 3 and e.passes_to_locate == 3
    keys = summary(s, set())
    assert keys["removal_median_passes"] == 3 and keys["false_revocations"] == 0


def test_a_move_needs_the_new_place_held_and_the_old_one_empty():
    sch = ChangeSchedule().with_move(SIGN, 0, 100.0, [0.0, 12.0])
    new_id = sch.changes[0].new_id
    s = ChangeScorer(WORLD, sch)
    drive_north(s, 110.0)
    both = landmarks([(7, CLS, X0, 0.0, 1, 1), (8, CLS, X0, 12.0, 0, 1)])
    s.check(120.0, both)
    assert s.events[0].waiting_for == [7]
    drive_north(s, 130.0)
    s.check(140.0, landmarks([(8, CLS, X0, 12.0, 0, 1)]))  # a candidate holds it
    e = s.events[0]
    assert e.passes_to_reflect == 2 and e.passes_to_locate is None
    drive_north(s, 150.0)
    s.check(160.0, landmarks([(8, CLS, X0, 12.2, 1, 1)]))  # now confirmed: located
    assert e.passes_to_locate == 3 and new_id not in e.waiting_for


def test_an_addition_held_by_a_doubtful_landmark_is_not_reflected():
    row = SIGN.take(np.array([0]))
    row = type(row)(**{**row.__dict__, "position": row.position + np.array([0.0, 40.0, 0.0])})
    sch = ChangeSchedule().with_addition(SIGN, 100.0, row)
    s = ChangeScorer(WORLD, sch)
    s.check(120.0, landmarks([(9, CLS, X0, 40.0, 1, 2)]))
    assert s.events[0].reflected_at is None
    s.check(130.0, landmarks([(9, CLS, X0, 40.0, 1, 1)]))
    assert s.events[0].reflected_at == 130.0


def test_a_standing_sign_the_map_loses_is_a_false_revocation_and_a_rogues_if_it_said_so():
    row = SIGN.take(np.array([0]))
    row = type(row)(**{**row.__dict__, "position": row.position + np.array([0.0, 40.0, 0.0])})
    sch = ChangeSchedule().with_addition(SIGN, 1e9, row)  # after the run: sign 0 unchanged
    s = ChangeScorer(WORLD, sch)
    s.check(10.0, landmarks([(7, CLS, X0, 0.0, 1, 1)]))
    s.check(20.0, landmarks([(7, CLS, X0, 0.0, 1, 2)]))  # doubtful: not held, not lost yet
    assert s.lost == {0: (20.0, 7)}
    keys = summary(s, {7})
    assert keys["false_revocations"] == 1 and keys["rogue_revocations"] == 1


def test_calibration_bins_and_brier():
    cal = calibration([(0.99, 1)] * 9 + [(0.99, 0), (0.1, 0)])
    assert cal["n"] == 11 and [b["n"] for b in cal["bins"]] == [1, 10]
    assert cal["bins"][1]["stood"] == 0.9
    assert abs(cal["brier"] - (9 * 0.01**2 + 0.99**2 + 0.1**2) / 11) < 1e-9
