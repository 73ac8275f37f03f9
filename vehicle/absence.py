"""Which mapped signs a pass should have seen, and which of them it did not detect
(issue 21: negative evidence for the map to follow the world).

Pure geometry on one pass, in a local East-North frame the caller chose (metres): the
camera's position and yaw at every frame of the pass (frames without detections
included: they are the evidence), the map's landmarks near the route with their class
and facing, and the pass's detections as (frame, class, bearing in the image). A
landmark is *in view* in a frame when it is inside the horizontal field of view, between
``min_range_m`` and ``max_range_m``, and the camera is on the side it is seen from (its
facing, :class:`schemas.map.MapLandmarks`, within ``facing_tol_deg``; any side while its
facing is unknown). It is *seen* when, in a frame where it is in view, a detection of its
class lies within ``bearing_gate_deg`` of its predicted bearing. An *absence* is a
landmark in view in at least ``min_frames`` frames and seen in none.

Pitfalls: occlusion (a parked truck) is not modelled: the share of frames in view and the
range go with each absence so that the server weighs it (a pass counts once); a map
landmark whose position is off by more than the gate's width at its range looks absent:
the gate must cover the landmark's and the pose's uncertainty. Given them (the frames'
yaw and position sigmas, the landmarks' position sigma), the gate in a frame is
``hypot(bearing_gate_deg, gate_sigmas * s)`` with ``s`` the predicted bearing's sigma:
``hypot(sigma_yaw, atan(hypot(sigma_camera, sigma_landmark) / range))`` (wider up close).
Where a detection has a range (from its box's size, with its sigma), it must also agree
with the landmark's range in that frame within ``gate_sigmas`` sigmas of the difference
(the detection's, the camera's and the landmark's), and ``range_slack_m``: a sign moved
along its street stands on nearly the same bearing as its old place, further on, and
would otherwise count as the old one seen.

>>> import numpy as np
>>> cam = np.stack([np.zeros(21), np.linspace(0.0, 40.0, 21)], 1)  # north along x = 0
>>> lm = np.array([[4.0, 30.0], [-4.0, 30.0]])  # right and left of the road, ahead
>>> frames = Frames(np.arange(21) * 0.1, cam, np.zeros(21))
>>> signs = MapSigns(np.array([11, 12]), lm, np.array([5, 5]), np.full(2, np.nan))
>>> bearing = np.degrees(np.arctan2(4.0, 30.0 - cam[:10, 1]))  # the right sign, first frames
>>> dets = FrameDetections(np.arange(10), np.full(10, 5), bearing)
>>> e = expected(frames, signs, dets, ViewModel())
>>> e.seen.tolist(), e.frames_in_view.tolist(), absent(e, ViewModel()).tolist()
([True, False], [14, 14], [False, True])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class ViewModel:
    """What the camera and its detector can see of a sign."""

    hfov_deg: float = 90.0
    """Horizontal field of view (the camera's: ``2 atan(width / 2 fx)``)."""
    min_range_m: float = 4.0
    max_range_m: float = 35.0
    """Farthest a sign is detected reliably (beyond: not evidence either way)."""
    facing_tol_deg: float = 80.0
    """A sign is in view only from within this angle of the direction it is seen from."""
    bearing_gate_deg: float = 4.0
    """A detection this close to the predicted bearing is the landmark (with no pose or
    landmark uncertainty: the detector's own error)."""
    gate_sigmas: float = 3.0
    """The gate widens by this many sigmas of the predicted bearing (module docstring)."""
    range_slack_m: float = 2.0
    """Added to the range gate (the panel's distance is not the sign's point)."""
    min_frames: int = 3
    """An absence needs the landmark in view in at least this many frames."""


@dataclass(frozen=True)
class Frames:
    """The pass's camera frames: time (s), position (F, 2) East-North m, yaw (deg,
    clockwise from North: the camera's axis), and optionally the standard deviations of
    the yaw (deg) and of the position (m, per horizontal axis); None: exact."""

    t: Array
    en: Array
    yaw_deg: Array
    sigma_yaw_deg: Array | None = None
    sigma_m: Array | None = None


@dataclass(frozen=True)
class MapSigns:
    """Map landmarks near the route: id, position (L, 2) East-North m, class, facing (deg
    clockwise from North, the direction the sign is seen from; NaN: unknown), and
    optionally the position's standard deviation (m, its largest horizontal axis); None:
    exact."""

    id: IntArray
    en: Array
    sign_class: IntArray
    facing_deg: Array
    sigma_m: Array | None = None


@dataclass(frozen=True)
class FrameDetections:
    """The pass's detections: frame index (into :class:`Frames`), class, bearing (deg,
    clockwise from the camera's axis)."""

    frame: IntArray
    sign_class: IntArray
    bearing_deg: Array
    range_m: Array | None = None
    """Per detection its range from the box's size, m (0: none); None: no ranges."""
    sigma_range_m: Array | None = None


@dataclass(frozen=True)
class Expected:
    """Per map landmark: frames in view, their share of the pass's frames, whether a
    detection matched it, and at its closest in-view frame the range (m), the bearing
    (deg, from the camera's axis) and the time (NaN where never in view)."""

    frames_in_view: IntArray
    share: Array
    seen: BoolArray
    range_m: Array
    bearing_deg: Array
    t: Array


def _wrap(deg: Array) -> Array:
    """Angles to [-180, 180)."""
    return (np.asarray(deg, float) + 180.0) % 360.0 - 180.0


def geometry(frames: Frames, signs: MapSigns) -> tuple[Array, Array, BoolArray]:
    """Range (F, L), bearing from the camera axis (F, L) and whether the camera is on the
    side each sign is seen from (F, L)."""
    v = signs.en[None, :, :] - frames.en[:, None, :]
    rng = np.hypot(v[..., 0], v[..., 1])
    az = np.degrees(np.arctan2(v[..., 0], v[..., 1]))  # clockwise from North
    bearing = _wrap(az - np.asarray(frames.yaw_deg, float)[:, None])
    back = az + 180.0  # from the sign toward the camera
    facing = np.asarray(signs.facing_deg, float)[None, :]
    off = np.abs(_wrap(back - np.where(np.isnan(facing), back, facing)))
    return rng, bearing, off


def gate_deg(frames: Frames, signs: MapSigns, rng: Array, model: ViewModel) -> Array:
    """The bearing gate per frame and landmark (F, L), deg (module docstring)."""
    f, n = rng.shape
    s_yaw = np.zeros(f) if frames.sigma_yaw_deg is None else np.asarray(frames.sigma_yaw_deg)
    s_cam = np.zeros(f) if frames.sigma_m is None else np.asarray(frames.sigma_m, float)
    s_lm = np.zeros(n) if signs.sigma_m is None else np.asarray(signs.sigma_m, float)
    s_pos = np.degrees(np.arctan2(np.hypot(s_cam[:, None], s_lm[None, :]), rng))
    s = np.hypot(np.asarray(s_yaw, float)[:, None], s_pos)
    return np.hypot(model.bearing_gate_deg, model.gate_sigmas * s)


def range_agrees(
    frames: Frames, signs: MapSigns, dets: FrameDetections, rng: Array, model: ViewModel
) -> BoolArray:
    """(D, L): whether each detection's box range agrees with each landmark's range in its
    frame (module docstring); a detection without a range (0) agrees with any."""
    f = np.asarray(dets.frame, np.int64)
    r = np.asarray(dets.range_m, float)
    s_r = np.zeros(r.size) if dets.sigma_range_m is None else np.asarray(dets.sigma_range_m)
    s_cam = np.zeros(len(frames.t)) if frames.sigma_m is None else np.asarray(frames.sigma_m)
    s_lm = np.zeros(len(signs.id)) if signs.sigma_m is None else np.asarray(signs.sigma_m)
    sigma = np.sqrt(s_r[:, None] ** 2 + s_cam[f][:, None] ** 2 + s_lm[None, :] ** 2)
    ok = np.abs(r[:, None] - rng[f]) <= model.gate_sigmas * sigma + model.range_slack_m
    return ok | (r <= 0)[:, None]


def expected(frames: Frames, signs: MapSigns, dets: FrameDetections, model: ViewModel) -> Expected:
    """The pass's view of each map landmark (module docstring)."""
    rng, bearing, off = geometry(frames, signs)
    in_view = (
        (np.abs(bearing) <= model.hfov_deg / 2.0)
        & (rng >= model.min_range_m)
        & (rng <= model.max_range_m)
        & (off <= model.facing_tol_deg)
    )
    seen = np.zeros(len(signs.id), bool)
    f = np.asarray(dets.frame, np.int64)
    if f.size:
        same = np.asarray(dets.sign_class)[:, None] == np.asarray(signs.sign_class)[None, :]
        gate = gate_deg(frames, signs, rng, model)[f]
        close = np.abs(_wrap(np.asarray(dets.bearing_deg)[:, None] - bearing[f])) <= gate
        if dets.range_m is not None:
            close &= range_agrees(frames, signs, dets, rng, model)
        seen = np.any(in_view[f] & same & close, axis=0)
    n = in_view.sum(axis=0)
    f_all, n_signs = rng.shape
    none = np.full((1, n_signs), np.nan)  # a row past the last frame: no view
    k = np.argmin(np.vstack([np.where(in_view, rng, np.inf), np.full_like(none, np.inf)]), axis=0)
    k = np.where(n > 0, k, f_all)  # the closest frame in view, or the row of no view
    cols = np.arange(n_signs)
    return Expected(
        frames_in_view=n.astype(np.int64),
        share=n / max(f_all, 1),
        seen=seen,
        range_m=np.vstack([rng, none])[k, cols],
        bearing_deg=np.vstack([bearing, none])[k, cols],
        t=np.append(np.asarray(frames.t, float), np.nan)[k],
    )


def absent(e: Expected, model: ViewModel) -> BoolArray:
    """The landmarks in view long enough and seen in no frame."""
    return (e.frames_in_view >= model.min_frames) & ~e.seen
