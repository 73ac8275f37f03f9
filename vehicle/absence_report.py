"""A pass's absences: the mapped signs it had in view and did not detect, as the wire table
:class:`schemas.Absences` (issue 21, vehicle side; the geometry is :mod:`vehicle.absence`).

**Frames.** The detector's SDK lists only the frames with detections, so the pass's usable
GNSS fixes stand for its frames: the camera pose at each fix (the antenna placed by the
fix, the camera by the mounts, yaw = the fix heading plus the camera's mounting yaw) in an
East-North frame at the first usable fix. ``frames`` and ``share`` of an absence count
these poses. Not used: fixes :func:`vehicle.geoloc.fix_outliers` finds suspect (as
:meth:`vehicle.agent.VehicleAgent.record` drops them) and fixes whose heading sigma
exceeds ``max_heading_sigma_deg`` (standing still: the course means nothing).

**Detections** are matched at their own frame's pose: interpolated at ``Detections.t``
from the fixes around it as :mod:`vehicle.pose` does (position linearly, heading on the
circle, the fixes' sigmas bounded and grown with the gap; a frame no fix reaches within
``PoseTiming.max_gap_s`` is dropped), or the fix of its image without times. A detection's
bearing from the camera axis is its ray's azimuth (the camera model of
:func:`vehicle.geoloc.geolocate`) less the axis's: it does not depend on the pose. A
detection matches at any bearing in the image and from any side, up to
``match_range_m`` (beyond the range that counts frames: a sign the detector saw farther
off still stands); the gate decides.

**Gate.** The detection's range from its box's size agrees with the landmark's
(:func:`vehicle.absence.range_agrees`), and its bearing lies within ``bearing_gate_deg``
widened by ``gate_sigmas`` sigmas of the predicted bearing
(:func:`vehicle.absence.gate_deg`): the heading's and the camera's position sigma
(the claim, at least ``heading_sigma_floor_deg`` / ``pose_sigma_floor_m``: many receivers
claim only their white error, the simulator's FLEET receiver 1 m of its 2.5 m bias) and
the landmark's (its covariance's largest horizontal axis). By default the widening is off
(``gate_sigmas`` 0: 4 degrees and 2 m): the vehicle's own test is strict, and where its
pose is off a sign it passed looks missed; the matcher, which linked the pass's rays to
that landmark, then takes it as seen (:mod:`hdmap.mapping.presence`: the rays decide).
Pitfall: a wide gate (3 sigmas of a 2 m pose error is 40 degrees at 8 m) takes a sign
moved 5-30 m along its street, on nearly the same bearing further on, for the old one:
with it only 14 of 64 passes past a moved sign reported the old place empty (with the
strict gate 55).

**Landmarks**: the map's rows the caller gives (those near the route), retired ones
excepted, candidates included (a ghost's absences help take it down).

Meridian convergence over a pass (hundredths of a degree per km) is ignored.

Pitfall: one call per whole pass. A pass cut in pieces reports, per piece, the signs
detected in another piece as absent.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from hdmap.geo.geodesy import EnuFrame
from schemas import STATUS_RETIRED, Absences
from schemas.map import MapLandmarks
from vehicle.absence import (
    FrameDetections,
    Frames,
    MapSigns,
    ViewModel,
    absent,
    expected,
)
from vehicle.geoloc import (
    DEFAULT_TIMING,
    Detections,
    FixCheck,
    GnssFixes,
    VehicleModel,
    angles_in_vehicle,
    box_range,
    fix_outliers,
    vehicle_to_enu,
)
from vehicle.pose import (
    PoseTiming,
    bracket,
    check_increasing,
    interpolate,
    interpolate_angle,
    interpolate_sigma,
    motion_sigma,
    reachable,
)

Array = NDArray[np.float64]

MAX_FRAMES = 100_000
"""``Absences.frames``'s upper bound on the wire (a longer view is clipped to it)."""


@dataclass(frozen=True)
class AbsenceConfig:
    """What counts as a sign a pass should have seen (module docstring)."""

    min_range_m: float = 4.0
    max_range_m: float = 35.0
    """Farthest a sign is detected reliably; lower where the camera's resolution makes the
    smallest panel shorter than ``VehicleModel.min_box_px`` (:func:`view_model`)."""
    fov_margin_deg: float = 3.0
    """Taken off each side of the horizontal field of view (a sign at the edge is cut)."""
    facing_tol_deg: float = 80.0
    bearing_gate_deg: float = 4.0
    gate_sigmas: float = 0.0
    pose_sigma_floor_m: float = 2.0
    heading_sigma_floor_deg: float = 1.0
    match_range_m: float = 60.0
    max_heading_sigma_deg: float = 10.0
    min_frames: int = 3

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_range_m < self.max_range_m <= self.match_range_m:
            raise ValueError("AbsenceConfig: need 0 <= min_range_m < max_range_m <= match_range_m")
        if self.min_frames < 1:
            raise ValueError("AbsenceConfig.min_frames must be at least 1")


DEFAULT_ABSENCE = AbsenceConfig()
DEFAULT_FIX_CHECK = FixCheck()


def view_model(model: VehicleModel, cfg: AbsenceConfig = DEFAULT_ABSENCE) -> ViewModel:
    """The view of this vehicle's camera: the horizontal field of view of its intrinsics
    (``2 atan(width / 2 fx)`` less the margins), the range the config and the resolution
    allow (the smallest panel of the catalogue at least ``min_box_px`` tall)."""
    intr = model.intrinsics
    hfov = 2.0 * np.degrees(np.arctan(intr.width / (2.0 * intr.fx))) - 2.0 * cfg.fov_margin_deg
    panel = float(np.min(model.catalog.heights(model.catalog.codes)))
    resolved = intr.fy * panel / max(model.min_box_px, 1.0)
    return ViewModel(
        hfov_deg=float(hfov),
        min_range_m=cfg.min_range_m,
        max_range_m=float(min(cfg.max_range_m, max(resolved, cfg.min_range_m + 1.0))),
        facing_tol_deg=cfg.facing_tol_deg,
        bearing_gate_deg=cfg.bearing_gate_deg,
        gate_sigmas=cfg.gate_sigmas,
        min_frames=cfg.min_frames,
    )


def _ray_azimuth_deg(model: VehicleModel, uv: Array) -> Array:
    """Azimuth of pixels' rays at heading 0 (deg clockwise from the vehicle's axis)."""
    _, az, _ = angles_in_vehicle(model.intrinsics, model.camera_mount, uv)
    return np.degrees(az)


def mounting_yaw_deg(model: VehicleModel) -> float:
    """The camera axis's azimuth from the vehicle's heading, deg (0: looking ahead)."""
    intr = model.intrinsics
    return float(_ray_azimuth_deg(model, np.array([[intr.cx, intr.cy]]))[0])


def detection_bearings(det: Detections, model: VehicleModel) -> Array:
    """Per detection: its box centre's bearing from the camera axis, deg clockwise."""
    box = np.asarray(det.box, float).reshape(-1, 4)
    uv = np.stack([(box[:, 0] + box[:, 2]) / 2.0, (box[:, 1] + box[:, 3]) / 2.0], axis=-1)
    return (_ray_azimuth_deg(model, uv) - mounting_yaw_deg(model) + 180.0) % 360.0 - 180.0


def map_signs(lm: MapLandmarks, frame: EnuFrame) -> tuple[MapSigns, NDArray[np.bool_]]:
    """The landmarks not retired, in ``frame``, with their position sigma; and which rows
    of ``lm`` they are."""
    keep = np.asarray(lm.status) != STATUS_RETIRED
    lm = lm.take(keep)
    en = frame.from_geodetic(lm.lat, lm.lon, lm.h).reshape(-1, 3)[:, :2]
    c = np.asarray(lm.cov, float).reshape(-1, 6)
    ee, en_, nn = c[:, 0], c[:, 1], c[:, 3]
    big = (ee + nn) / 2.0 + np.sqrt(((ee - nn) / 2.0) ** 2 + en_**2)
    facing, _, _ = lm.facing()
    signs = MapSigns(
        id=np.asarray(lm.id, np.uint64).astype(np.int64),
        en=en,
        sign_class=np.asarray(lm.sign_class, np.int64),
        facing_deg=facing,
        sigma_m=np.sqrt(np.maximum(big, 0.0)),
    )
    return signs, keep


def _camera_frames(
    t: Array, xyz: Array, psi: Array, s_h: Array, s_psi: Array, model: VehicleModel
) -> Frames:
    """Camera frames from antenna poses (ENU m, heading rad) and their sigmas (m, rad)."""
    lever = model.camera_mount.t - model.gnss_mount.t
    cam = xyz + np.einsum("nij,j->ni", vehicle_to_enu(psi), lever)
    lever_xy = float(np.hypot(lever[0], lever[1]))
    return Frames(
        t=np.asarray(t, float),
        en=cam[:, :2],
        yaw_deg=np.degrees(psi) + mounting_yaw_deg(model),
        sigma_yaw_deg=np.degrees(s_psi),
        sigma_m=np.hypot(s_h, s_psi * lever_xy),
    )


def _floored(frames: Frames, cfg: AbsenceConfig) -> Frames:
    """``frames`` with their sigmas at least the config's floors."""
    return replace(
        frames,
        sigma_yaw_deg=np.maximum(np.asarray(frames.sigma_yaw_deg), cfg.heading_sigma_floor_deg),
        sigma_m=np.maximum(np.asarray(frames.sigma_m), cfg.pose_sigma_floor_m),
    )


def _take(frames: Frames, rows: NDArray) -> Frames:
    """Some of ``frames`` (a mask or indices)."""
    return Frames(*(None if v is None else np.asarray(v)[rows] for v in frames.__dict__.values()))


def detection_frames(
    fixes: GnssFixes,
    xyz: Array,
    det: Detections,
    model: VehicleModel,
    timing: PoseTiming = DEFAULT_TIMING,
) -> tuple[Frames, FrameDetections]:
    """The camera pose at each detection's frame (one per image number) and the
    detections that have one, indexing those frames (module docstring). ``fixes`` are the
    usable ones and ``xyz`` their antenna positions (ENU m); without ``det.t``,
    ``det.image`` indexes them (-1 or beyond: no pose)."""
    psi = np.radians(np.asarray(fixes.heading_deg, float))
    s_h = np.asarray(fixes.sigma_h_m, float)
    s_psi = np.radians(np.asarray(fixes.sigma_heading_deg, float))
    image = np.asarray(det.image, np.int64)
    if image.size == 0:
        e = np.zeros(0)
        return Frames(e, np.zeros((0, 2)), e, e, e), FrameDetections(image, image, e)
    if det.t is None:
        ok = (image >= 0) & (image < len(fixes))
        img, row = np.unique(image[ok], return_inverse=True)
        frames = _camera_frames(
            np.asarray(fixes.t, float)[img], xyz[img], psi[img], s_h[img], s_psi[img], model
        )
    else:
        _, first, row_all = np.unique(image, return_index=True, return_inverse=True)
        t = np.asarray(det.t, float)[first]
        ft = check_increasing(fixes.t, "GnssFixes.t")
        has = reachable(bracket(ft, t), timing) & np.isfinite(t)
        ok = has[row_all]
        keep = np.flatnonzero(has)
        br = bracket(ft, t[keep])
        s_pos = np.hypot(interpolate_sigma(br, s_h), motion_sigma(br, timing.accel_sigma_mps2))
        s_yaw = np.hypot(
            interpolate_sigma(br, s_psi), motion_sigma(br, timing.yaw_accel_sigma_radps2)
        )
        frames = _camera_frames(
            t[keep], interpolate(br, xyz), interpolate_angle(br, psi), s_pos, s_yaw, model
        )
        row = np.cumsum(has)[row_all[ok]] - 1  # index among the frames kept
    r, s_r = box_range(np.asarray(det.box, float).reshape(-1, 4), np.asarray(det.sign_class), model)
    dets = FrameDetections(
        frame=np.asarray(row, np.int64),
        sign_class=np.asarray(det.sign_class, np.int64)[ok],
        bearing_deg=detection_bearings(det, model)[ok],
        range_m=r[ok],
        sigma_range_m=s_r[ok],
    )
    return frames, dets


def pass_absences(
    fixes: GnssFixes,
    det: Detections,
    landmarks: MapLandmarks,
    model: VehicleModel,
    cfg: AbsenceConfig = DEFAULT_ABSENCE,
    timing: PoseTiming = DEFAULT_TIMING,
    fix_check: FixCheck | None = DEFAULT_FIX_CHECK,
) -> Absences:
    """The landmarks of ``landmarks`` the pass had in view in at least ``min_frames`` of
    its fixes' frames and detected in none (module docstring), one row each."""
    good = np.ones(len(fixes), bool)
    if fix_check is not None:
        good = ~fix_outliers(fixes, fix_check)
    use = fixes.take(np.flatnonzero(good))
    if len(use) == 0 or len(landmarks) == 0:
        return Absences.empty()
    lat, lon, h = (np.asarray(getattr(use, k), float) for k in ("lat", "lon", "h"))
    frame = EnuFrame(float(lat[0]), float(lon[0]), float(h[0]))
    xyz = frame.from_geodetic(lat, lon, h).reshape(-1, 3)
    signs, rows = map_signs(landmarks, frame)
    view = view_model(model, cfg)

    psi = np.radians(np.asarray(use.heading_deg, float))
    s_psi = np.radians(np.asarray(use.sigma_heading_deg, float))
    at_fix = _camera_frames(use.t, xyz, psi, np.asarray(use.sigma_h_m, float), s_psi, model)
    steady = np.asarray(use.sigma_heading_deg, float) <= cfg.max_heading_sigma_deg
    if not steady.any():
        return Absences.empty()
    none = FrameDetections(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    e = expected(_take(at_fix, steady), signs, none, view)

    if det.t is None:  # the index form: image numbers index all the fixes
        det = replace(det, image=_reindex(det.image, good))
    d_frames, d_dets = detection_frames(use, xyz, det, model, timing)
    anywhere = ViewModel(
        hfov_deg=360.0,
        min_range_m=0.0,
        max_range_m=cfg.match_range_m,
        facing_tol_deg=180.0,
        bearing_gate_deg=cfg.bearing_gate_deg,
        gate_sigmas=cfg.gate_sigmas,
        range_slack_m=view.range_slack_m,
        min_frames=1,
    )
    seen = expected(_floored(d_frames, cfg), signs, d_dets, anywhere).seen
    miss = absent(replace(e, seen=seen), view)
    return Absences(
        landmark_id=np.asarray(landmarks.id, np.uint64)[rows][miss],
        t=e.t[miss],
        frames=np.minimum(e.frames_in_view[miss], MAX_FRAMES).astype(np.uint32),
        share=np.clip(e.share[miss], 0.0, 1.0).astype(np.float32),
        range_m=e.range_m[miss].astype(np.float32),
        bearing_deg=e.bearing_deg[miss].astype(np.float32),
    )


def _reindex(image: NDArray, good: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Indices into all fixes -> indices into the good ones (-1: a suspect or no fix)."""
    idx = np.asarray(image, np.int64)
    new = np.cumsum(good) - 1
    inside = (idx >= 0) & (idx < good.size)
    out = np.full(idx.shape, -1, np.int64)
    out[inside] = np.where(good[idx[inside]], new[idx[inside]], -1)
    return out
