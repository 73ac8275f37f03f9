"""Onboard localisation against the map: where the vehicle is, better than its GNSS says.

A pass's detections are matched to the landmarks of the map it follows
(:meth:`vehicle.mapclient.MapClient.near`), and the matches measure what the receiver's
fixes are off by; the pose at a query time is the GNSS pose less that offset, with a
covariance (the arithmetic: :mod:`vehicle.localizer_solve`). Pure numpy, no I/O; what it
does per query time ``t`` uses only the fixes and detections up to ``t`` (online).

**Detections** whose box touches the image's border are not used: the detector cuts the
box there, and its centre is no longer the sign's (a bearing off by a tenth of a metre at
20 m, where the others are good to a few centimetres). Nor are those whose pose claims a
heading sigma over ``max_heading_sigma_deg`` (slow in a corner, a course over ground).

**Poses.** Fixes that jump off their neighbours' track are dropped
(:func:`vehicle.geoloc.fix_outliers`); the GNSS pose at a time is interpolated from the
others (:func:`vehicle.geoloc.antenna_poses`); each detection's ray is
:func:`vehicle.geoloc.geolocate`'s (camera centre, azimuth and its sigma, range from the box
size, the pose's white sigma), all in an East-North frame at the pass's first usable fix.
A query time no fix reaches within ``PoseTiming.max_gap_s`` has no pose (NaN).

**Matching**, frame by frame in time order, against the estimate of the last query time
(the prior before any; its covariance grown by the offset's random walk since): the
candidates of a detection are the landmarks of its class, not retired (confirmed ones only
by default), that stand between ``min_range_m`` and ``max_range_m`` of the camera placed by
that estimate, inside its horizontal field of view (widened by ``fov_margin_deg``), and
are seen from the camera's side (their facing within ``facing_tol_deg`` of the direction
from the sign toward the camera; any side while unknown). A candidate passes the gate
when the chi-square of its innovation (the across row, and the along row where the box
gives a range) against the pose's covariance projected, the fix's white error, the
landmark's covariance and the ray's noise is under the ``gate_prob`` quantile
(:func:`vehicle.localizer_solve.gate_pairs`); within a frame one detection takes one
landmark and one landmark one detection, at least total cost (chi-square plus the
log-determinant of its covariance;
:func:`hdmap.mapping.association.assign_per_image`).

**The offset**, per query time: weighted least squares over the matches of the last
``window_s`` seconds (:func:`vehicle.localizer_solve.solve`), with two tests on each
match left out of it (deletion residuals, so that what is tested does not pull the
estimate it is tested against): the landmark whose matches put it furthest from its map
position beyond the ``landmark_prob`` quantile is left out (a landmark the map holds
metres off its sign), then the matches whose residual is beyond the ``residual_prob``
quantile (a ray of a corner, a wrong neighbour that passed the gate), and the window is
solved again, up to ``max_rejections`` rounds; a match left out is tried again at the
next query. A window is **inconsistent** when its offset is outside the GNSS prior's
``residual_prob`` region (or its heading bias outside its prior's) or the residual test
left out more than ``max_rejected_share`` of its matches: its matches are dropped for
good and the gate goes back to the prior (a wrong estimate gates in wrong matches that
agree with it). A **map-aided fix** needs a consistent window with matches of at least
``min_landmarks`` distinct landmarks; otherwise the output is the GNSS pose with the GNSS
error model's covariance (the prior plus the fix's white error), flagged not map-aided.

**The pose out** is the GNSS pose less the offset at the query time: the slow offset and
the fix's white error there, which the rays of frames within ``corr_s`` share and so
tell; **its covariance** is the joint one, with the landmarks' covariance taken as
shared by all of them in the part ``map_correlation`` (a map's error that every landmark
shares does not average down over more of them; :mod:`vehicle.localizer_solve`).

Invariant (docs/localization.md): uploads keep raw GNSS poses. A map-aided pose folded
into the observations a vehicle uploads would count the map twice: the landmark would be
re-estimated from rays placed by itself, and its covariance would shrink with no new
information.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.geodesy import EnuFrame
from hdmap.mapping.association import assign_per_image
from schemas import STATUS_CONFIRMED, STATUS_RETIRED
from schemas.map import MapLandmarks
from vehicle.absence_report import mounting_yaw_deg
from vehicle.geoloc import (
    DEFAULT_TIMING,
    Detections,
    FixCheck,
    GnssFixes,
    VehicleModel,
    antenna_poses,
    detection_reach,
    fix_outliers,
    geolocate,
)
from vehicle.localizer_solve import (
    Solution,
    chi2_quantile,
    gate_pairs,
    pair_rows,
    solve,
    stack_rows,
)
from vehicle.pose import PoseTiming

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class LocalizerConfig:
    """The localiser's error model and tests (module docstring)."""

    prior_sigma_m: float = 3.0
    """The GNSS offset's prior, m per horizontal axis (at least what the fixes claim): a
    consumer receiver's total error in town, multipath aside."""
    walk_m_per_sqrt_s: float = 0.2
    """The offset's random walk, m per sqrt(s) per axis."""
    heading_bias_sigma_deg: float = 1.5
    """Prior of the heading's bias over the window, deg."""
    corr_s: float = 1.0
    """The fix's white error and the heading's hold for about this long, s (rays this far
    apart share none of them; :func:`vehicle.localizer_solve.solve`)."""
    window_s: float = 30.0
    """Matches older than this before the query time are not used."""
    max_window_matches: int = 160
    """At most this many matches (the latest) per solve."""
    gate_prob: float = 0.999
    residual_prob: float = 0.999
    landmark_prob: float = 0.999
    """A landmark whose matches put it further from its map position than this quantile
    of its covariance and theirs is left out of the window's solve
    (:func:`vehicle.localizer_solve.landmark_test`)."""
    max_rejections: int = 6
    max_rejected_share: float = 0.25
    """A window whose residual test leaves out more of its matches is inconsistent: no
    map-aided fix, its matches dropped, the gate back on the GNSS prior."""
    min_landmarks: int = 3
    min_range_m: float = 3.0
    max_range_m: float = 60.0
    fov_margin_deg: float = 5.0
    max_heading_sigma_deg: float = 3.0
    """Detections whose pose claims a larger heading sigma are not used (slow in a corner:
    a course over ground's error grows as the speed falls; such rays open the gate to the
    neighbours of the sign and tell little)."""
    facing_tol_deg: float = 80.0
    confirmed_only: bool = True
    """Match only confirmed landmarks (a candidate may be a ghost)."""
    map_correlation: float = 1.0
    """Share of the landmarks' covariance taken as shared by all of them in the
    covariance reported (1: none of it averages down)."""
    fix_check: FixCheck | None = field(default_factory=FixCheck)

    def __post_init__(self) -> None:
        for name in ("prior_sigma_m", "window_s", "max_range_m"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"LocalizerConfig.{name}: must be > 0")
        for name in ("walk_m_per_sqrt_s", "heading_bias_sigma_deg", "min_range_m"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"LocalizerConfig.{name}: must be >= 0")
        for name in ("gate_prob", "residual_prob", "landmark_prob"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise ValueError(f"LocalizerConfig.{name}: must be in (0, 1)")
        if not 0.0 <= self.map_correlation <= 1.0:
            raise ValueError("LocalizerConfig.map_correlation: must be in [0, 1]")
        if self.min_landmarks < 1 or self.max_window_matches < 1:
            raise ValueError("LocalizerConfig: min_landmarks and max_window_matches >= 1")


DEFAULT_LOCALIZER = LocalizerConfig()


@dataclass(frozen=True)
class LocalizedPoses:
    """Per query time: the GNSS pose and the localiser's (struct of arrays; East-North
    metres in :attr:`frame`, the GNSS antenna's position; NaN where no fix reaches)."""

    frame: EnuFrame
    t: Array
    gnss_en: Array
    """(N, 2) the GNSS pose."""
    gnss_cov: Array
    """(N, 2, 2) its covariance under the localiser's GNSS error model."""
    en: Array
    """(N, 2) the output: map-aided where :attr:`map_aided`, else the GNSS pose."""
    cov: Array
    map_aided: NDArray[np.bool_]
    offset: Array
    """(N, 2) the estimated GNSS offset at the query time (what the fix there is off by:
    the slow offset and the fix's white error), m; the prior's mean (0) without matches."""
    offset_cov: Array
    """(N, 2, 2) its covariance (with the map's shared error; the output's :attr:`cov`
    where map-aided)."""
    heading_bias_rad: Array
    n_landmarks: IntArray
    """Distinct landmarks matched in the window (after rejections)."""
    n_matches: IntArray
    landmark_ids: list[NDArray[np.uint64]]
    """Per query time: the map ids of the landmarks used."""
    landmark_gains: list[Array]
    """Per query time (L, 2, 2): the output moves by ``sum_j gains_j m_j`` for map errors
    ``m_j`` of those landmarks (East-North, m)."""
    matches: Matches

    def geodetic(self) -> tuple[Array, Array]:
        """The output positions' latitude and longitude, deg."""
        lat, lon, _ = self.frame.to_geodetic(np.column_stack([self.en, np.zeros(len(self.t))]))
        return np.atleast_1d(lat), np.atleast_1d(lon)


@dataclass(frozen=True)
class Matches:
    """Every match made over the pass: detection row (of the ``Detections`` given),
    landmark id, time, and whether the last solve that saw it left it out (the tests, or
    an inconsistent window)."""

    detection: IntArray
    landmark_id: NDArray[np.uint64]
    t: Array
    rejected: NDArray[np.bool_]


@dataclass(frozen=True)
class _Rays:
    """The pass's usable detections as rays in the pass's frame."""

    row: IntArray
    frame: IntArray
    t: Array
    cls: IntArray
    cam: Array
    yaw_rad: Array
    """The camera axis's azimuth (fix heading plus the mounting yaw)."""
    az: Array
    r_h: Array
    sigma_az: Array
    """The azimuth's sigma from the pixels alone (the heading's apart)."""
    sigma_heading: Array
    sigma_r: Array
    range_rel: Array
    """The relative sigma of the sign's panel size (shared by every look at one sign)."""
    sigma_w: Array


@dataclass(frozen=True)
class _Map:
    id: NDArray[np.uint64]
    en: Array
    cov: Array
    cls: IntArray
    facing_rad: Array


def _map_in(frame: EnuFrame, lm: MapLandmarks, confirmed_only: bool) -> _Map:
    keep = np.asarray(lm.status) != STATUS_RETIRED
    if confirmed_only:
        keep &= np.asarray(lm.status) == STATUS_CONFIRMED
    lm = lm.take(np.flatnonzero(keep))
    en = frame.from_geodetic(lm.lat, lm.lon, lm.h).reshape(-1, 3)[:, :2]
    c = np.asarray(lm.cov, float).reshape(-1, 6)
    cov = np.stack([np.stack([c[:, 0], c[:, 1]], -1), np.stack([c[:, 1], c[:, 3]], -1)], 1)
    facing, _, _ = lm.facing()
    return _Map(
        id=np.asarray(lm.id, np.uint64),
        en=en,
        cov=cov,
        cls=np.asarray(lm.sign_class, np.int64),
        facing_rad=np.radians(np.asarray(facing, float)),
    )


def _rays(
    frame: EnuFrame,
    fixes: GnssFixes,
    det: Detections,
    model: VehicleModel,
    timing: PoseTiming,
    max_heading: float = np.inf,
) -> _Rays:
    reach = detection_reach(fixes, det, timing)
    intr = model.intrinsics
    box = np.asarray(det.box, float).reshape(-1, 4)
    inside = (
        (box[:, 0] >= 1.0)
        & (box[:, 1] >= 1.0)
        & (box[:, 2] <= intr.width - 2.0)
        & (box[:, 3] <= intr.height - 2.0)
    )
    rows = np.flatnonzero(reach & inside)
    if rows.size:
        steady = antenna_poses(fixes, det.take(rows), timing).sigma_heading_rad <= max_heading
        rows = rows[steady]
    d = det.take(rows)
    lines = geolocate(fixes, d, model, timing=timing)
    pose = antenna_poses(fixes, d, timing)
    cam = frame.from_geodetic(lines.lat, lines.lon, lines.h).reshape(-1, 3)[:, :2]
    v = frame.vectors_from_enu_at(lines.direction, lines.lat, lines.lon).reshape(-1, 3)
    horiz = np.hypot(v[:, 0], v[:, 1])
    cos_el = horiz / np.maximum(np.linalg.norm(v, axis=1), 1e-12)
    t = np.asarray(lines.t, float)
    s_head = np.asarray(pose.sigma_heading_rad, float)
    _, frame_id = np.unique(np.round(t, 6), return_inverse=True)
    return _Rays(
        row=rows.astype(np.int64),
        frame=frame_id.astype(np.int64),
        t=t,
        cls=np.asarray(lines.sign_class, np.int64),
        cam=cam,
        yaw_rad=np.asarray(pose.heading_rad, float) + np.radians(mounting_yaw_deg(model)),
        az=np.arctan2(v[:, 0], v[:, 1]),
        r_h=np.asarray(lines.range_m, float) * cos_el,
        sigma_az=np.sqrt(np.maximum(np.asarray(lines.sigma_az, float) ** 2 - s_head**2, 0.0)),
        sigma_heading=s_head,
        sigma_r=np.asarray(lines.sigma_range_m, float) * cos_el,
        range_rel=np.asarray(model.catalog.rel_sigmas(lines.sign_class), float),
        sigma_w=np.asarray(lines.sigma_pos_h, float),
    )


def _wrap(a: ArrayLike) -> Array:
    return (np.asarray(a, float) + np.pi) % (2.0 * np.pi) - np.pi


class _Matcher:
    """Gates and assigns one frame's detections (module docstring)."""

    def __init__(self, rays: _Rays, mp: _Map, model: VehicleModel, cfg: LocalizerConfig):
        self.rays, self.mp, self.cfg = rays, mp, cfg
        intr = model.intrinsics
        half = np.degrees(np.arctan(intr.width / (2.0 * intr.fx))) + cfg.fov_margin_deg
        self.half_fov = np.radians(half)
        self.gate = {1: chi2_quantile(1, cfg.gate_prob), 2: chi2_quantile(2, cfg.gate_prob)}

    def frame(self, idx: IntArray, theta: Array, p_theta: Array) -> tuple[IntArray, IntArray]:
        """(ray indices, map rows) matched in one frame's rays ``idx``."""
        r, mp, cfg = self.rays, self.mp, self.cfg
        di, li = np.nonzero(r.cls[idx][:, None] == mp.cls[None, :])
        if di.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        k = idx[di]
        cam = r.cam[k] - theta[:2]  # the camera placed by the estimate
        v = mp.en[li] - cam
        dist = np.hypot(v[:, 0], v[:, 1])
        az = np.arctan2(v[:, 0], v[:, 1])
        bearing = _wrap(az - (r.yaw_rad[k] - theta[2]))
        back = az + np.pi  # from the sign toward the camera
        facing = mp.facing_rad[li]
        off = np.abs(_wrap(back - np.where(np.isnan(facing), back, facing)))
        ok = (
            (dist >= cfg.min_range_m)
            & (dist <= cfg.max_range_m)
            & (np.abs(bearing) <= self.half_fov)
            & (off <= np.radians(cfg.facing_tol_deg))
        )
        di, li, k = di[ok], li[ok], k[ok]
        if di.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        rows = pair_rows(
            r.cam[k],
            r.az[k],
            r.r_h[k],
            mp.en[li],
            r.sigma_az[k],
            r.sigma_r[k],
            r.range_rel[k],
            r.sigma_heading[k],
        )
        chi2, logdet, dof = gate_pairs(rows, theta, p_theta, r.sigma_w[k], mp.cov[li])
        limit = np.where(dof == 2, self.gate[2], self.gate[1])
        ok = np.isfinite(chi2) & (chi2 <= limit)
        if not ok.any():
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        di, li, cost = di[ok], li[ok], (chi2 + logdet)[ok]
        cost = cost - cost.min() + 1.0  # the assignment wants costs below its sentinel
        best = assign_per_image(idx.size, np.zeros(idx.size, np.int64), di, li, cost, np.inf)
        got = np.flatnonzero(best >= 0)
        return idx[got], best[got]


def localize(
    fixes: GnssFixes,
    det: Detections,
    landmarks: MapLandmarks,
    model: VehicleModel,
    t_query: ArrayLike,
    cfg: LocalizerConfig = DEFAULT_LOCALIZER,
    timing: PoseTiming = DEFAULT_TIMING,
) -> LocalizedPoses:
    """The pass's poses at ``t_query`` (s, on the fixes' clock; any order), map-aided where
    the matches allow (module docstring). ``landmarks``: the map near the route."""
    tq = np.asarray(t_query, float).reshape(-1)
    order = np.argsort(tq, kind="stable")
    good = np.ones(len(fixes), bool)
    if cfg.fix_check is not None:
        good = ~fix_outliers(fixes, cfg.fix_check)
    use = fixes.take(np.flatnonzero(good))
    if len(use) == 0:
        raise ValueError("GnssFixes: no usable fix")
    lat0, lon0, h0 = (float(np.asarray(getattr(use, k))[0]) for k in ("lat", "lon", "h"))
    frame = EnuFrame(lat0, lon0, h0)
    if det.t is None:  # the index form: each detection at its image's fix
        det = Detections(
            det.image,
            det.sign_class,
            det.box,
            det.score,
            np.asarray(fixes.t, float)[np.asarray(det.image, np.int64)],
        )
    rays = _rays(frame, use, det, model, timing, np.radians(cfg.max_heading_sigma_deg))
    mp = _map_in(frame, landmarks, cfg.confirmed_only)

    s_prior = max(cfg.prior_sigma_m, float(np.median(np.asarray(use.sigma_h_m, float))))
    p0 = np.diag([s_prior**2, s_prior**2, np.radians(cfg.heading_bias_sigma_deg) ** 2])
    q2 = cfg.walk_m_per_sqrt_s**2
    limits = {
        "1": chi2_quantile(1, cfg.residual_prob),
        "2": chi2_quantile(2, cfg.residual_prob),
        "lm1": chi2_quantile(1, cfg.landmark_prob),
        "lm2": chi2_quantile(2, cfg.landmark_prob),
    }

    # the GNSS pose at the query times
    n = tq.size
    gnss_en = np.full((n, 2), np.nan)
    white = np.full(n, np.nan)
    qd = Detections(np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros((n, 4)), np.zeros(n), tq)
    at = np.flatnonzero(detection_reach(use, qd, timing))
    if at.size:
        qp = antenna_poses(use, qd.take(at), timing)
        gnss_en[at] = frame.from_geodetic(qp.lat, qp.lon, qp.h).reshape(-1, 3)[:, :2]
        white[at] = qp.sigma_h_m

    frames_t = np.array(
        [rays.t[rays.frame == f][0] for f in range(int(rays.frame.max()) + 1)]
        if len(rays.t)
        else []
    )
    f_order = np.argsort(frames_t, kind="stable")
    matcher = _Matcher(rays, mp, model, cfg)
    m_ray: list[int] = []
    m_lm: list[int] = []
    theta, p_theta, t_est = np.zeros(3), p0.copy(), None
    state = np.zeros(0, np.int8)
    out = _Outputs(n)
    fi = 0
    for qi in order.tolist():
        t = tq[qi]
        while fi < f_order.size and frames_t[f_order[fi]] <= t:
            f = int(f_order[fi])
            fi += 1
            idx = np.flatnonzero(rays.frame == f)
            p_now = p_theta
            if t_est is not None:
                grow = q2 * max(frames_t[f] - t_est, 0.0)
                p_now = p_theta + np.diag([grow, grow, 0.0])
            got_r, got_l = matcher.frame(idx, theta, p_now)
            m_ray += got_r.tolist()
            m_lm += got_l.tolist()
        state = np.r_[state, np.zeros(len(m_ray) - state.size, np.int8)]
        wq = float(white[qi]) if np.isfinite(white[qi]) else 0.0
        sol, ok = _solve_window(
            rays,
            mp,
            np.array(m_ray, np.int64),
            np.array(m_lm, np.int64),
            state,
            t,
            p0,
            cfg,
            limits,
            wq,
        )
        if ok:
            theta, p_theta, t_est = sol.theta, sol.p_post, t
        else:  # start again from the GNSS prior
            theta, p_theta, t_est = np.zeros(3), p0.copy(), None
        out.put(qi, sol, mp, ok)
    aided = out.consistent & (out.n_landmarks >= cfg.min_landmarks)
    cov_gnss = (s_prior**2 + white**2)[:, None, None] * np.eye(2)
    en = np.where(aided[:, None], gnss_en - out.offset, gnss_en)
    cov = np.where(aided[:, None, None], out.cov, cov_gnss)
    return LocalizedPoses(
        frame=frame,
        t=tq,
        gnss_en=gnss_en,
        gnss_cov=cov_gnss,
        en=en,
        cov=cov,
        map_aided=aided & np.isfinite(gnss_en[:, 0]),
        offset=out.offset,
        offset_cov=out.cov,
        heading_bias_rad=out.dpsi,
        n_landmarks=out.n_landmarks,
        n_matches=out.n_matches,
        landmark_ids=out.ids,
        landmark_gains=out.gains,
        matches=Matches(
            detection=rays.row[np.array(m_ray, np.int64)] if m_ray else np.zeros(0, np.int64),
            landmark_id=mp.id[np.array(m_lm, np.int64)] if m_lm else np.zeros(0, np.uint64),
            t=rays.t[np.array(m_ray, np.int64)] if m_ray else np.zeros(0),
            rejected=state != LIVE,
        ),
    )


LIVE, REJECTED, DROPPED = 0, 1, 2
"""A match's state: used by the last solve of its window, left out of it by the residual
test (tried again at the next), or dropped for good with an inconsistent window."""


def _solve_window(
    rays: _Rays,
    mp: _Map,
    m_ray: IntArray,
    m_lm: IntArray,
    state: NDArray[np.int8],
    t: float,
    p0: Array,
    cfg: LocalizerConfig,
    limits: dict[str, float],
    sigma_wq: float,
) -> tuple[Solution, bool]:
    """The window's solution at ``t`` and whether it is consistent. Each round leaves out
    the matches failing the residual test and solves again (``state`` keeps the last
    verdict); the solution is inconsistent when the offset it finds is beyond the GNSS
    prior's ``residual_prob`` region, or the test left out more than
    ``max_rejected_share`` of the window's matches. An inconsistent window's matches are
    dropped for good (their gating followed a wrong estimate)."""
    window = (
        np.flatnonzero(
            (state != DROPPED) & (rays.t[m_ray] >= t - cfg.window_s) & (rays.t[m_ray] <= t)
        )
        if m_ray.size
        else np.zeros(0, np.int64)
    )
    window = window[-cfg.max_window_matches :]
    live = window
    n_bad = 0  # matches left out by the matches' test (not with their landmark)
    for _round in range(cfg.max_rejections + 1):
        k, j = m_ray[live], m_lm[live]
        rows = pair_rows(
            rays.cam[k],
            rays.az[k],
            rays.r_h[k],
            mp.en[j],
            rays.sigma_az[k],
            rays.sigma_r[k],
            rays.range_rel[k],
            rays.sigma_heading[k],
        )
        st = stack_rows(rows, live, j, rays.frame[k], rays.t[k], rays.sigma_w[k])
        sol = solve(
            st, t, p0, cfg.walk_m_per_sqrt_s, mp.cov, cfg.map_correlation, cfg.corr_s, sigma_wq
        )
        if sol.matches.size == 0 or _round == cfg.max_rejections:
            break
        # the worst landmark failing its test goes first (all its matches); then the matches
        lm_limit = np.where(sol.landmark_dof == 2, limits["lm2"], limits["lm1"])
        excess = np.where(sol.landmark_dof > 0, sol.landmark_chi2 / lm_limit, 0.0)
        if excess.size and excess.max() > 1.0:
            worst = sol.landmarks[int(np.argmax(excess))]
            live = live[m_lm[live] != worst]
            continue
        bad = sol.matches[sol.match_chi2 > np.where(sol.match_dof == 2, limits["2"], limits["1"])]
        if bad.size == 0:
            break
        n_bad += bad.size
        live = np.setdiff1d(live, bad)
    state[window] = REJECTED
    state[live] = LIVE
    b = sol.theta[:2]
    off = float(b @ np.linalg.solve(p0[:2, :2], b))
    tilt = float(sol.theta[2] ** 2 / p0[2, 2])
    left_out = n_bad / max(window.size, 1)
    ok = off <= limits["2"] and tilt <= limits["1"] and left_out <= cfg.max_rejected_share
    if not ok:
        state[window] = DROPPED
    return sol, ok


class _Outputs:
    """The per-query results as they are filled in."""

    def __init__(self, n: int):
        self.offset = np.full((n, 2), np.nan)
        self.dpsi = np.full(n, np.nan)
        self.cov = np.full((n, 2, 2), np.nan)
        self.n_landmarks = np.zeros(n, np.int64)
        self.n_matches = np.zeros(n, np.int64)
        self.ids: list[NDArray[np.uint64]] = [np.zeros(0, np.uint64)] * n
        self.gains: list[Array] = [np.zeros((0, 2, 2))] * n
        self.consistent = np.zeros(n, bool)

    def put(self, qi: int, sol: Solution, mp: _Map, ok: bool) -> None:
        self.consistent[qi] = ok
        self.offset[qi] = sol.offset
        self.dpsi[qi] = sol.theta[2]
        self.cov[qi] = sol.offset_cov
        self.n_landmarks[qi] = sol.landmarks.size
        self.n_matches[qi] = sol.matches.size
        self.ids[qi] = mp.id[sol.landmarks]
        self.gains[qi] = sol.gains
