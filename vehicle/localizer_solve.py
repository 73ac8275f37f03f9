"""The map-aided localiser's arithmetic: detections against map landmarks as measurements
of the GNSS offset, their gate, and the window's weighted least squares
(:mod:`vehicle.localizer` runs them over a pass).

**Unknowns** ``theta = (b_e, b_n, dpsi)``: the GNSS offset at the query time (what the
receiver's fixes are off by, East and North, m: the camera placed by a fix stands at
``c_true + b + w``, ``w`` the fix's white error) and the heading's bias (rad; the fix
heading is ``psi_true + dpsi + white``). A prior ``N(0, P0)`` stands for the receiver's
error model before any match.

**One detection** at a camera placed at ``c`` (the GNSS pose), measured azimuth ``a``
(clockwise from North) and, where its box gives one, horizontal range ``r``, matched to a
map landmark at ``L`` (covariance ``Sigma``). With ``u = (sin a, cos a)`` along the ray
and ``n = (cos a, -sin a)`` across it (the direction in which the azimuth grows):

    across:  y = n . (c - L)       = n . b + r dpsi + n . (w - m) + r e_a
    along:   y = r + u . (c - L)   = u . b           + u . (w - m) + e_r

to first order, ``m`` the landmark's map error, ``e_a`` the azimuth's white error (pixels
and heading, the ray's ``sigma_az``), ``e_r`` the range's. Without a range only the
across row is used (its ``r`` is then the distance to the landmark).

**What is shared.** Rows of one frame share the fix's white error ``w`` (sigma
``sigma_w``: the pose's, :func:`vehicle.geoloc.geolocate`'s ``sigma_pos_h``). The offset
is a random walk (``q`` m per sqrt(s)): a row taken ``tau = t_query - t`` before the
query measures ``b(t_query)`` less the walk since, and two rows share the walk after the
later of them (covariance ``q^2 min(tau_i, tau_k)``). Every row of one landmark shares
its map error ``m``. The weights take the landmarks' errors as independent of each other
(:func:`solve`); the covariance reported does not: the part ``map_correlation`` of the
map's error is taken as shared by all the landmarks (a map built by a fleet whose
receivers share an error carries it everywhere; the solver's floors are shared terms),
and that part does not average down with more landmarks (the sandwich of
:func:`solve`).

>>> # a camera 10 m South of its landmark sees it due North at 10 m: nothing to explain;
>>> # the across row measures the offset's East and the heading (times the range), the
>>> # along row its North
>>> rows = pair_rows(np.zeros((1, 2)), np.zeros(1), np.array([10.0]), np.array([[0.0, 10.0]]))
>>> (rows.y + 0.0).tolist(), (rows.h[0] + 0.0).tolist()
([[0.0, 0.0]], [[1.0, 0.0, 10.0], [0.0, 1.0, 0.0]])
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def chi2_quantile(dof: int, p: float) -> float:
    """The ``p`` quantile of chi-square with 1 or 2 degrees of freedom (no scipy onboard).

    >>> round(chi2_quantile(1, 0.95), 3), round(chi2_quantile(2, 0.95), 3)
    (3.841, 5.991)
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"p: must be in (0, 1), got {p!r}")
    if dof == 1:
        return NormalDist().inv_cdf((1.0 + p) / 2.0) ** 2
    if dof == 2:
        return -2.0 * float(np.log1p(-p))
    raise ValueError(f"dof: 1 or 2, got {dof!r}")


@dataclass(frozen=True)
class PairRows:
    """Per (detection, landmark) pair its two rows (across, along): values (K, 2),
    Jacobians (K, 2, 3) in ``theta``, the offset's part of them (K, 2, 2: ``n`` and ``u``),
    the rays' own white variances (K, 2), the sigma of their error every ray of the same
    landmark shares (K, 2: the along row's panel-size part of the range), the sigma of
    the heading's error in them (K, 2: the across row's ``r sigma_heading``) and whether
    the along row is used (K,)."""

    y: Array
    h: Array
    a: Array
    var: Array
    shared: Array
    heading: Array
    has_range: NDArray[np.bool_]


def pair_rows(
    cam: Array,
    az: Array,
    r_h: Array,
    lm: Array,
    sigma_az: Array | None = None,
    sigma_r: Array | None = None,
    range_rel: Array | None = None,
    sigma_heading: Array | None = None,
) -> PairRows:
    """The rows of pairs (module docstring): camera positions (K, 2), measured azimuths
    (K,) rad, horizontal ranges (K,) m (0: none), landmark positions (K, 2); the rays'
    azimuth (pixels alone) and range sigmas (None: 0), of the range's relative sigma the
    part a sign keeps at every look (``range_rel``: its panel's size off the class's
    nominal one; None: 0), taken out of the range's white variance and shared by the rays
    of one landmark, and the heading's sigma (rad; None: 0), which rays close in time
    share (:func:`solve`)."""
    cam = np.asarray(cam, float).reshape(-1, 2)
    lm = np.asarray(lm, float).reshape(-1, 2)
    az = np.asarray(az, float).reshape(-1)
    r_h = np.asarray(r_h, float).reshape(-1)
    k = az.size
    u = np.stack([np.sin(az), np.cos(az)], -1)
    n = np.stack([np.cos(az), -np.sin(az)], -1)
    d = cam - lm
    has = r_h > 0.0
    dist = np.hypot(d[:, 0], d[:, 1])
    r = np.where(has, r_h, dist)
    y = np.stack([np.sum(n * d, -1), np.where(has, r_h + np.sum(u * d, -1), 0.0)], -1)
    h = np.zeros((k, 2, 3))
    h[:, 0, :2] = n
    h[:, 0, 2] = r
    h[:, 1, :2] = u
    a = np.stack([n, u], 1)
    s_az = np.zeros(k) if sigma_az is None else np.asarray(sigma_az, float).reshape(-1)
    s_r = np.zeros(k) if sigma_r is None else np.asarray(sigma_r, float).reshape(-1)
    rel = np.zeros(k) if range_rel is None else np.asarray(range_rel, float).reshape(-1)
    shared_r = np.where(has, r_h * rel, 0.0)
    white_r2 = np.maximum(s_r**2 - shared_r**2, (0.01 * r_h) ** 2)
    var = np.stack([(r * s_az) ** 2, np.where(has, white_r2, 1.0)], -1)
    shared = np.stack([np.zeros(k), shared_r], -1)
    s_h = np.zeros(k) if sigma_heading is None else np.asarray(sigma_heading, float).reshape(-1)
    heading = np.stack([r * s_h, np.zeros(k)], -1)
    return PairRows(y=y, h=h, a=a, var=var, shared=shared, heading=heading, has_range=has)


def gate_pairs(
    rows: PairRows,
    theta: Array,
    p_theta: Array,
    sigma_w: Array,
    lm_cov: Array,
) -> tuple[Array, Array, IntArray]:
    """Per pair: the chi-square of its innovation ``y - H theta`` against ``H P H' +
    A (sigma_w^2 I + Sigma) A' + diag(var)`` (the pose's covariance projected, the fix's
    white error, the landmark's covariance, the ray's own noise), the log-determinant of
    that covariance, and its degrees of freedom (1: across only; 2: with the range)."""
    nu = rows.y - np.einsum("kij,j->ki", rows.h, np.asarray(theta, float))
    s = np.einsum("kij,jl,kml->kim", rows.h, p_theta, rows.h)
    pos = np.asarray(sigma_w, float)[:, None, None] ** 2 * np.eye(2) + lm_cov
    s = s + np.einsum("kij,kjl,kml->kim", rows.a, pos, rows.a)
    s[:, 0, 0] += rows.var[:, 0] + rows.shared[:, 0] ** 2 + rows.heading[:, 0] ** 2
    s[:, 1, 1] += rows.var[:, 1] + rows.shared[:, 1] ** 2
    has = rows.has_range
    det2 = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] ** 2
    det2 = np.where(det2 > 0.0, det2, np.nan)
    chi2_two = (
        s[:, 1, 1] * nu[:, 0] ** 2
        - 2.0 * s[:, 0, 1] * nu[:, 0] * nu[:, 1]
        + s[:, 0, 0] * nu[:, 1] ** 2
    ) / det2
    chi2_one = nu[:, 0] ** 2 / s[:, 0, 0]
    chi2 = np.where(has, chi2_two, chi2_one)
    logdet = np.where(has, np.log(det2), np.log(s[:, 0, 0]))
    return chi2, logdet, np.where(has, 2, 1).astype(np.int64)


@dataclass(frozen=True)
class Stacked:
    """The window's rows, flattened (M rows): values, Jacobians (M, 3), offset parts (M, 2),
    ray variances, the sigma of the error the rows of one landmark share and of the
    heading's error, and per row
    its match (index into the caller's matches), landmark (index into the map), frame,
    time, and its fix's white sigma."""

    y: Array
    h: Array
    a: Array
    var: Array
    shared: Array
    heading: Array
    match: IntArray
    landmark: IntArray
    frame: IntArray
    t: Array
    sigma_w: Array

    def __len__(self) -> int:
        return int(self.y.size)


def stack_rows(
    rows: PairRows,
    match: IntArray,
    landmark: IntArray,
    frame: IntArray,
    t: Array,
    sigma_w: Array,
) -> Stacked:
    """Pairs' rows (one or two each) as one list of rows (:class:`Stacked`)."""
    k = rows.y.shape[0]
    use = np.stack([np.ones(k, bool), rows.has_range], -1).reshape(-1)
    rep = np.repeat(np.arange(k), 2)[use]
    return Stacked(
        y=rows.y.reshape(-1)[use],
        h=rows.h.reshape(-1, 3)[use],
        a=rows.a.reshape(-1, 2)[use],
        var=rows.var.reshape(-1)[use],
        shared=rows.shared.reshape(-1)[use],
        heading=rows.heading.reshape(-1)[use],
        match=np.asarray(match, np.int64)[rep],
        landmark=np.asarray(landmark, np.int64)[rep],
        frame=np.asarray(frame, np.int64)[rep],
        t=np.asarray(t, float)[rep],
        sigma_w=np.asarray(sigma_w, float)[rep],
    )


@dataclass(frozen=True)
class Solution:
    """The window's estimate at the query time.

    ``theta`` and ``p_post`` are the weighted least squares' estimate and its covariance
    under the weights' model (the landmarks' errors independent); ``offset`` what the fix
    at the query time is off by (``b`` and the fix's white error there, :func:`solve`) and
    ``offset_cov`` its covariance with the shared part of the map's error (module
    docstring), the one to report.
    ``match_chi2`` / ``match_dof`` the normalised residual of each match in the window
    (its one or two rows against their residual covariance), ``landmarks`` the map rows
    used and ``gains`` (L, 2, 2) how their map errors move the offset's estimate:
    ``offset_hat - offset = -sum_j gains_j m_j + ...``; ``landmark_chi2`` / ``landmark_dof`` the
    landmarks' test (:func:`landmark_test`)."""

    theta: Array
    p_post: Array
    offset: Array
    offset_cov: Array
    matches: IntArray
    match_chi2: Array
    match_dof: IntArray
    landmarks: IntArray
    gains: Array
    landmark_chi2: Array
    """Per landmark used: the chi-square of the displacement its rows' residuals put on
    it (its map error as they see it) against its covariance and that displacement's."""
    landmark_dof: IntArray


def solve(
    rows: Stacked,
    t_query: float,
    p0: Array,
    walk: float,
    lm_cov: Array,
    map_correlation: float,
    corr_s: float = 0.0,
    sigma_wq: float = 0.0,
) -> Solution:
    """Weighted least squares for ``theta`` at ``t_query`` over the window's rows with the
    prior ``N(0, p0)``, the noise model of the module docstring; ``lm_cov`` (N, 2, 2) the
    map's horizontal covariances (rows index them by ``rows.landmark``). The fix's white
    error and the heading's are shared by rows ``dt`` apart in proportion
    ``max(0, 1 - |dt| / corr_s)`` (a receiver's error that holds for about ``corr_s``
    seconds: a 1 Hz receiver's, interpolated; 0: by the rows of one frame only).

    The offset reported is the fix's error at ``t_query``: ``b`` and the fix's white error
    there (sigma ``sigma_wq``), which the rows within ``corr_s`` of it share and so tell
    (the conditional mean given the rows: ``w_hat = c_q P y``, ``c_q`` its covariance with
    the rows, ``P`` their predictive precision); its covariance is the joint one, plus the
    shared part of the map's error."""
    p0 = np.asarray(p0, float)
    p0_inv = np.linalg.inv(p0)
    m = len(rows)
    if m == 0:
        e = np.zeros(0, np.int64)
        s0 = p0[:2, :2] + sigma_wq**2 * np.eye(2)
        return Solution(
            np.zeros(3),
            p0,
            np.zeros(2),
            s0,
            e,
            np.zeros(0),
            e,
            e,
            np.zeros((0, 2, 2)),
            np.zeros(0),
            e,
        )
    a = rows.a
    aa = a @ a.T
    tau = np.maximum(t_query - rows.t, 0.0)
    c = np.diag(rows.var)
    if corr_s > 0.0:
        near = np.maximum(1.0 - np.abs(rows.t[:, None] - rows.t[None, :]) / corr_s, 0.0)
    else:
        near = (rows.frame[:, None] == rows.frame[None, :]).astype(float)
    c += near * (np.outer(rows.sigma_w, rows.sigma_w) * aa + np.outer(rows.heading, rows.heading))
    c += walk**2 * np.minimum(tau[:, None], tau[None, :]) * aa
    sig = lm_cov[rows.landmark]  # (M, 2, 2)
    v = np.einsum("mij,mj->mi", sig, a)
    same_lm = rows.landmark[:, None] == rows.landmark[None, :]
    c += same_lm * np.outer(rows.shared, rows.shared)
    c += same_lm * (v @ a.T)
    c = (c + c.T) / 2.0
    ci = np.linalg.solve(c, np.column_stack([rows.h, rows.y]))
    ci_h, ci_y = ci[:, :3], ci[:, 3]
    info = rows.h.T @ ci_h + p0_inv
    p_post = np.linalg.inv(info)
    p_post = (p_post + p_post.T) / 2.0
    theta = p_post @ (rows.h.T @ ci_y)
    gain = p_post @ ci_h.T  # (3, M): theta_hat = gain y
    ci_full = np.linalg.inv(c)
    pred = ci_full - ci_h @ p_post @ ci_h.T  # the precision of y's prior predictive
    g = ci_full @ rows.y - ci_h @ theta  # = pred @ y
    # the fix's white error at the query time, from the rows that share it (kriging)
    cq = np.zeros((2, m))
    if sigma_wq > 0.0 and corr_s > 0.0:
        k = np.maximum(1.0 - np.abs(rows.t - t_query) / corr_s, 0.0)
        cq = (sigma_wq * rows.sigma_w * k)[None, :] * a.T
    w_hat = cq @ g
    out_gain = gain[:2] + cq @ pred  # offset_hat = out_gain y
    cross = -gain[:2] @ cq.T  # Cov(b - b_hat, w - w_hat)
    offset_cov = p_post[:2, :2] + sigma_wq**2 * np.eye(2) - cq @ pred @ cq.T + cross + cross.T
    # the map's error: m_j enters row i as -a_i' m_j
    lms, inv = np.unique(rows.landmark, return_inverse=True)
    gd = np.zeros((lms.size, 2, 2))
    np.add.at(gd, inv, np.einsum("im,mj->mij", out_gain, a))
    if map_correlation > 0.0 and lms.size > 1:
        sig_l = lm_cov[lms]
        root = _sqrtm_2x2(sig_l)
        shared = np.einsum("lij,ljk->ik", gd, root)
        own = np.einsum("lij,ljk,lmk->im", gd, sig_l, gd)
        offset_cov = offset_cov + map_correlation * (shared @ shared.T - own)
    offset_cov = (offset_cov + offset_cov.T) / 2.0
    # the tests: each match's rows and each landmark's rows against the rest (left out)
    ids, first, dof = np.unique(rows.match, return_index=True, return_counts=True)
    second = np.where(dof > 1, first + 1, first)  # a match's rows are consecutive
    chi2 = _left_out_chi2(pred, g, first, second, dof > 1)
    lm_chi2, lm_dof = landmark_test(a, g, pred, inv)
    return Solution(
        theta=theta,
        p_post=p_post,
        offset=theta[:2] + w_hat,
        offset_cov=offset_cov,
        matches=ids.astype(np.int64),
        match_chi2=chi2,
        match_dof=dof.astype(np.int64),
        landmarks=lms.astype(np.int64),
        gains=gd,
        landmark_chi2=lm_chi2,
        landmark_dof=lm_dof,
    )


def _left_out_chi2(
    pred: Array, g: Array, first: IntArray, second: IntArray, two: NDArray[np.bool_]
) -> Array:
    """Per match (rows ``first`` and, where ``two``, ``second``): ``g_i' (P_ii)^-1 g_i``,
    the chi-square of its rows' residual given every other row (the deletion residual
    ``P_ii^-1 g_i`` with covariance ``P_ii^-1``; ``P`` the predictive precision, ``g =
    P y``)."""
    p00 = pred[first, first]
    p11 = np.where(two, pred[second, second], 1.0)
    p01 = np.where(two, pred[first, second], 0.0)
    det = p00 * p11 - p01**2
    g0, g1 = g[first], np.where(two, g[second], 0.0)
    both = (p11 * g0**2 - 2.0 * p01 * g0 * g1 + p00 * g1**2) / np.where(two, det, 1.0)
    return np.where(two, both, g0**2 / p00)


def landmark_test(a: Array, g: Array, pred: Array, which: IntArray) -> tuple[Array, IntArray]:
    """Per landmark (rows ``which == j``, offset parts ``a``): the score test of a
    displacement ``d`` of it given every other landmark's rows. Left out, its rows'
    residual is ``e = P_jj^-1 g_j`` with covariance ``P_jj^-1`` (``P`` the predictive
    precision, ``g = P y``; the landmark's own map covariance is in it); a displacement
    moves it by ``-A d``, so ``chi2 = (A' g_j)' (A' P_jj A)^+ (A' g_j)``, with as many
    degrees of freedom as the rows fix directions (1 or 2). Left out, the landmark does
    not pull the estimate it is tested against: a landmark the map holds metres off its
    sign (a confirmed copy built along one line of sight) stands out, and the landmarks
    that agree with each other do not."""
    n = int(which.max()) + 1 if which.size else 0
    chi2 = np.zeros(n)
    dof = np.zeros(n, np.int64)
    for j in range(n):
        r = np.flatnonzero(which == j)
        aj = a[r]
        f = aj.T @ pred[np.ix_(r, r)] @ aj
        ga = aj.T @ g[r]
        w, vec = np.linalg.eigh((f + f.T) / 2.0)
        keep = w > 1e-9 * max(float(w.max()), 1e-12)
        z = vec[:, keep].T @ ga
        chi2[j] = float(np.sum(z * z / w[keep]))
        dof[j] = int(keep.sum())
    return chi2, dof


def _sqrtm_2x2(s: Array) -> Array:
    """Symmetric square roots of (L, 2, 2) covariances (negative eigenvalues clipped)."""
    w, v = np.linalg.eigh(s)
    return np.einsum("lij,lj,lkj->lik", v, np.sqrt(np.maximum(w, 0.0)), v)
