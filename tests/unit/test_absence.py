"""Which mapped signs a pass should have seen and did not (vehicle/absence.py), on a
straight drive north along x = 0 from y = 0 to 60 m, 10 frames a second at 10 m/s, the
camera looking ahead (yaw 0, 90 degree field of view, signs detected from 4 to 35 m).

Signs: A 4 m right at y = 40 (seen: detected in every frame it is in view), B 4 m left at
y = 40 (never detected: absent), C 4 m right at y = 40 facing south-to-north traffic's
back (seen from the north: not in view), D 60 m east (never within range), E behind the
start (y = -20: never ahead), F the class of A at A's place 1 m further (a detection of
A's bearing is within F's gate at long range only).
"""

from __future__ import annotations

import numpy as np
import pytest

from vehicle.absence import FrameDetections, Frames, MapSigns, ViewModel, absent, expected

N = 61
CAM = np.stack([np.zeros(N), np.linspace(0.0, 60.0, N)], 1)
FRAMES = Frames(np.arange(N) * 0.1, CAM, np.zeros(N))


def signs(*rows: tuple[int, float, float, int, float]) -> MapSigns:
    a = np.array(rows, float)
    return MapSigns(a[:, 0].astype(np.int64), a[:, 1:3], a[:, 3].astype(np.int64), a[:, 4])


def detections_of(at: tuple[float, float], cls: int, model: ViewModel, shift_deg: float = 0.0):
    """A detector that sees the sign at ``at`` in every frame where it is in the field of
    view and range, at its true bearing plus ``shift_deg``."""
    v = np.asarray(at) - CAM
    rng = np.hypot(v[:, 0], v[:, 1])
    bearing = np.degrees(np.arctan2(v[:, 0], v[:, 1]))
    ok = (np.abs(bearing) <= model.hfov_deg / 2) & (rng >= model.min_range_m)
    ok &= rng <= model.max_range_m
    f = np.flatnonzero(ok)
    return FrameDetections(f, np.full(f.size, cls), bearing[f] + shift_deg)


M = ViewModel()
SCENE = signs(
    (1, 4.0, 40.0, 7, np.nan),  # A
    (2, -4.0, 40.0, 7, 180.0),  # B, seen from the south (where the car comes from)
    (3, 4.0, 40.0, 8, 0.0),  # C, seen from the north only
    (4, 60.0, 30.0, 7, np.nan),  # D
    (5, 3.0, -20.0, 7, np.nan),  # E
)


def test_a_sign_detected_is_seen_one_never_detected_is_absent_the_others_not_expected():
    e = expected(FRAMES, SCENE, detections_of((4.0, 40.0), 7, M), M)
    assert e.seen.tolist() == [True, False, False, False, False]
    assert absent(e, M).tolist() == [False, True, False, False, False]
    n = e.frames_in_view.tolist()
    assert n[0] == n[1] > 10 and n[2:] == [0, 0, 0]  # C faces away, D too far, E behind
    assert e.share[1] == pytest.approx(n[1] / N)
    # closest in view: the last frame before 4 m or 45 degrees off the axis
    assert 5.0 <= e.range_m[1] <= 6.0 and -46.0 <= e.bearing_deg[1] <= -44.0
    assert np.isnan(e.range_m[2]) and np.isnan(e.t[3])


@pytest.mark.parametrize("cls, shift, seen", [(7, 0.0, True), (9, 0.0, False), (7, 6.0, False)])
def test_a_detection_counts_only_with_the_class_and_within_the_gate(cls, shift, seen):
    one = signs((1, 4.0, 40.0, 7, np.nan))
    e = expected(FRAMES, one, detections_of((4.0, 40.0), cls, M, shift), M)
    assert e.seen.tolist() == [seen] and absent(e, M).tolist() == [not seen]


def test_too_few_frames_in_view_is_no_evidence():
    short = Frames(FRAMES.t[:7], CAM[:7], np.zeros(7))  # ends 34 m before the sign
    e = expected(short, signs((1, 4.0, 40.0, 7, np.nan)), FrameDetections(*[np.zeros(0)] * 3), M)
    assert 0 < e.frames_in_view[0] < M.min_frames and not absent(e, M)[0]


def test_the_camera_yaw_turns_the_field_of_view():
    """Looking east (yaw 90), a sign west of the road is never in view and one east of it
    is."""
    east = Frames(FRAMES.t, CAM, np.full(N, 90.0))
    e = expected(east, signs((1, -4.0, 40.0, 7, np.nan), (2, 20.0, 10.0, 7, np.nan)),
                 FrameDetections(*[np.zeros(0, np.int64)] * 3), M)  # fmt: skip
    assert e.frames_in_view[0] == 0 and e.frames_in_view[1] > 20
    assert absent(e, M).tolist() == [False, True]


def test_a_sign_moved_along_the_street_is_not_taken_for_the_old_one_when_ranges_are_given():
    """The map has the sign at y = 40; it now stands 14 m further on (y = 54), on nearly
    the same bearing from afar (the detector sees it up to 60 m): by bearing alone the old
    place counts as seen; the detections' box ranges tell the two apart (the strict gate
    the vehicle uses: 4 degrees, 2 m). The sign still at its place is seen with them."""
    strict = ViewModel(gate_sigmas=0.0)
    old = signs((1, 4.0, 40.0, 7, np.nan))

    def ranged(at: tuple[float, float]) -> FrameDetections:
        d = detections_of(at, 7, ViewModel(max_range_m=60.0))
        r = np.hypot(*(np.asarray(at) - CAM[d.frame]).T)
        return FrameDetections(d.frame, d.sign_class, d.bearing_deg, r, 0.1 * r)

    moved = ranged((4.0, 54.0))
    bearing_only = FrameDetections(moved.frame, moved.sign_class, moved.bearing_deg)
    assert expected(FRAMES, old, bearing_only, strict).seen.tolist() == [True]
    e = expected(FRAMES, old, moved, strict)
    assert e.seen.tolist() == [False] and absent(e, strict).tolist() == [True]
    assert expected(FRAMES, old, ranged((4.0, 40.0)), strict).seen.tolist() == [True]
