"""Looming: how a panel's box grows as the car drives up says where the panel is along the
line of sight, whatever its size. O(1) sums per landmark that give, at any trial point,
how far beyond the panel the point lies.

With :mod:`hdmap.mapping.box_ranges`' relative range ``u(x) = d . (x - a) / r`` of a ray
and its inverse box range ``v = 1 / r``: a panel ``s`` times its class's nominal size at
``P`` gives ``r = t / s`` (``t`` the true distance), so at ``x = P + delta d``

    u = (t + delta) s / t = s + delta v,

exactly, for every ray of the panel: a straight line in ``v`` whose intercept is the
panel's size and whose **slope is the distance ``delta`` from the panel to ``x`` along
the rays**. The slope is fitted within each pass (about the pass's own mean ``v``) and
pooled over the passes, each by its spread in ``v``: only how each pass's boxes grow
counts, not how passes seen from different distances differ, since their shared errors
differ too (with the phones' errors a fit across passes put a landmark 8 m beyond its
sign 2 m short of it). A pass's shared origin error ``b`` tilts its rays' line by ``-d .
b``, so the slope's variance has ``tau^2 m2`` (:func:`offset`; about ``tau^2 / n`` for
``n`` passes alike) on top of the rays' white part ``c / S`` (``c`` their white noise as
measured about the passes' lines over the claimed); ``tau`` is measured too, from how the
passes' own slopes scatter about the pooled one (:func:`shared_error`: on the simulated
receiver 3.0 m, on the phones' errors 1.4 m; the same for most landmarks).

Pitfall: a box's relative height error ``e`` is in the regressor too (``v = s (1 + e) /
t``), which biases the slope by about ``s^2 sigma_e^2 mean(1/t) / var(1/t)``. Simulated
(8 head-on passes from 30-80 m to 10 m, boxes of 600 px m / distance): with 2 px of
noise on the box height the mean slope is 0.27 m off and ``t`` keeps its spread; with
4.24 px (42 % on a 10 px box at 60 m) 1.2 m off, ``t``'s mean square 2.1 and 1.75 % of
right landmarks past 3 (0.27 % under the model). A check at 3 sigma turns those into
candidates; a fusion would move them.

State (:func:`summed`): per pass, with ``h`` and ``w`` from
:func:`hdmap.mapping.box_ranges.ray_terms`, the slope's numerator about the pass's mean
``v`` (linear in the trial point), its denominator, what the pass's shared error does to
it, and the residuals about the pass's line (quadratic in the trial point), which measure
the rays' white noise against their claim, and the pass's own slope's square; summed
over passes, :data:`N_SUMS` numbers per landmark, kept in its home tile's frame. They add
when landmarks merge and follow a rigid change of frame (:func:`in_frame`).

>>> from hdmap.mapping import box_ranges
>>> a = np.array([[0.0, -60.0, 0.0], [0.0, -40.0, 0.0], [0.0, -20.0, 0.0], [0.0, -10.0, 0.0]])
>>> d = np.tile([0.0, 1.0, 0.0], (4, 1))  # looking North at a panel at the origin
>>> r = np.array([60.0, 40.0, 20.0, 10.0]) / 1.2  # a panel 1.2 times its nominal size
>>> h, w = box_ranges.ray_terms(a, d, r, r * 0.1, 0.5, 0.1)
>>> sums = summed(np.zeros(4, np.int64), np.zeros(4, np.int64), h, w)  # one pass
>>> delta, var, g, m2 = offset(sums, np.array([[0.0, 7.0, 0.0]]))  # 7 m beyond the panel
>>> round(float(delta[0]), 6), g.round(6).tolist(), round(float(m2[0]), 6)
(7.0, [[0.0, 1.0, 0.0]], 1.0)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

N_SUMS = 29
"""Numbers a landmark keeps, summed over its passes: ``N_p`` (4), ``S_p``, ``|N_p[:3]|^2``,
the residual form ``M_p`` (10: a 4 x 4 symmetric matrix's upper triangle), its degrees
of freedom, then what the passes' own slopes need (:func:`shared_error`): ``N_p N_p^T /
S_p`` (10), ``|N_p[:3]|^2 / S_p`` and the pass's count (:func:`pass_sums`)."""

SHARED_PRIOR_PASSES = 4.0
"""Pseudo passes at the configured shared error in :func:`shared_error` (a landmark of few
passes keeps about the configured value)."""

RAW = 22
"""Numbers an open pass keeps (:func:`raw_terms` summed): ``sum w``, ``sum w v``, ``sum w
v^2``, ``sum w h[:4]``, ``sum w v h[:4]``, ``sum w h[:4] h[:4]^T`` (10) and its ranged
rays; :func:`pass_sums` turns them into the pass's share of a landmark's sums once all its
rays are in."""

NOISE_PRIOR_DOF = 4.0
"""Pseudo degrees of freedom at the claimed white noise in :func:`offset`'s measured
ratio ``c`` (a landmark of few rays keeps about its claim)."""

_IU = np.triu_indices(4)


def _sym(upper: Array) -> Array:
    """(k, 10) upper triangles -> (k, 4, 4) symmetric matrices."""
    m = np.zeros((len(upper), 4, 4))
    m[:, _IU[0], _IU[1]] = upper
    m[:, _IU[1], _IU[0]] = upper
    return m


def raw_terms(h: Array, w: Array) -> Array:
    """Per ray its :data:`RAW` terms (n, 22) from its box-range terms ``h`` (n, 5) and
    weight ``w`` (n,; 0: adds nothing)."""
    hh = np.asarray(h, float).reshape(-1, 5)
    ww = np.asarray(w, float).reshape(-1)
    v = np.linalg.norm(hh[:, :3], axis=1)
    outer = hh[:, _IU[0]] * hh[:, _IU[1]]
    return np.concatenate(
        [
            np.stack([ww, ww * v, ww * v * v], 1),
            ww[:, None] * hh[:, :4],
            (ww * v)[:, None] * hh[:, :4],
            ww[:, None] * outer,
            (ww > 0).astype(float)[:, None],
        ],
        axis=1,
    )


def pass_sums(raw: ArrayLike) -> Array:
    """Each pass's share (k, ``N_SUMS``) of its landmark's sums from its raw sums (k,
    :data:`RAW`): about the pass's own weighted mean inverse range ``vbar``, ``N = sum w
    (v - vbar) h[:4]`` (``N . (x, 1)`` is the slope's numerator at ``x``), ``S = sum w (v -
    vbar)^2``, ``|N[:3]|^2``, and ``M = sum w h h^T - H H^T / W - N N^T / S`` (``H = sum
    w h[:4]``, ``W = sum w``): ``(x, 1)^T M (x, 1)`` is the weighted squared residual of
    the pass's rays about its fitted line at ``x``, with ``n - 2`` degrees of freedom; then
    ``N N^T / S`` (its form at ``(x, 1)`` is ``S`` times the pass's own slope squared),
    ``|N[:3]|^2 / S`` and 1 (0 where the pass's inverse ranges do not spread)."""
    per = np.asarray(raw, float).reshape(-1, RAW)
    w, wv = per[:, 0], per[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        vbar = np.where(w > 0, wv / w, 0.0)
        hw = np.where(w[:, None] > 0, per[:, 3:7] / w[:, None], 0.0)
    n_p = per[:, 7:11] - vbar[:, None] * per[:, 3:7]
    s_p = per[:, 2] - vbar * wv
    with np.errstate(divide="ignore", invalid="ignore"):
        n_s = np.where(s_p[:, None] > 0, n_p / s_p[:, None], 0.0)
    m = _sym(per[:, 11:21])
    m -= per[:, 3:7, None] * hw[:, None, :]
    m -= n_p[:, :, None] * n_s[:, None, :]
    m = 0.5 * (m + np.transpose(m, (0, 2, 1)))
    dof = np.maximum(per[:, 21] - 2.0, 0.0)
    nn = np.einsum("ki,ki->k", n_p[:, :3], n_p[:, :3])
    return np.concatenate(
        [
            n_p,
            s_p[:, None],
            nn[:, None],
            m[:, _IU[0], _IU[1]] * (dof > 0)[:, None],
            dof[:, None],
            n_p[:, _IU[0]] * n_s[:, _IU[1]],
            np.einsum("ki,ki->k", n_p[:, :3], n_s[:, :3])[:, None],
            (s_p > 0).astype(float)[:, None],
        ],
        axis=1,
    )


def _lin4(rot: Array | None, t: Array | None) -> Array | None:
    """How ``h[:4]`` maps from frame F to G (``h_G = L h_F``); None: the same frame."""
    if rot is None or t is None:
        return None
    lin = np.eye(4)
    lin[:3, :3] = rot
    lin[3, :3] = -(np.asarray(t, float) @ rot)
    return lin


def raw_in_frame(raw: ArrayLike, rot: Array | None, t: Array | None) -> Array:
    """Open passes' raw sums kept in frame F as they are in frame G (``x_G = rot x_F +
    t``)."""
    r = np.asarray(raw, float).reshape(-1, RAW)
    out = r.copy()
    lin = _lin4(rot, t)
    if lin is None:
        return out
    out[:, 3:7] = r[:, 3:7] @ lin.T
    out[:, 7:11] = r[:, 7:11] @ lin.T
    out[:, 11:21] = (lin @ _sym(r[:, 11:21]) @ lin.T)[:, _IU[0], _IU[1]]
    return out


def summed(group: ArrayLike, piece: ArrayLike, h: Array, w: Array) -> Array:
    """Rays summed by the landmark each went to (``group``: 0, 1, ... per ray), (k,
    ``N_SUMS``); ``piece`` (0, 1, ... per ray) says which rays are one pass's (each piece
    within one group; :func:`pass_sums`). A pass cut into two pieces counts as two: each
    is centred on its own (unbiased, less precise: the slope within each piece only) and
    the pass's shared error's share is underestimated by the pieces' cross term."""
    g = np.asarray(group, np.int64).reshape(-1)
    pc = np.asarray(piece, np.int64).reshape(-1)
    npc = int(pc.max(initial=-1)) + 1
    per = np.zeros((npc, RAW))
    np.add.at(per, pc, raw_terms(h, w))
    owner = np.zeros(npc, np.int64)
    owner[pc] = g
    out = np.zeros((int(g.max(initial=-1)) + 1, N_SUMS))
    np.add.at(out, owner, pass_sums(per))
    return out


def in_frame(sums: ArrayLike, rot: Array | None, t: Array | None) -> Array:
    """Sums kept in frame F as they are in frame G, ``x_G = rot x_F + t`` (``N`` maps like
    a box-range ``h``, ``M`` on both sides; the rest does not change)."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    out = s.copy()
    lin = _lin4(rot, t)
    if lin is None:
        return out
    out[:, :4] = s[:, :4] @ lin.T
    out[:, 6:16] = (lin @ _sym(s[:, 6:16]) @ lin.T)[:, _IU[0], _IU[1]]
    out[:, 17:27] = (lin @ _sym(s[:, 17:27]) @ lin.T)[:, _IU[0], _IU[1]]
    return out


def offset(sums: ArrayLike, x: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """(delta, var, g, m2) at trial points ``x`` (k, 3; the sums' frame): the fitted slope
    ``delta = N . (x, 1) / S`` (how far beyond the panel ``x`` lies along the rays,
    metres; NaN where no pass's inverse ranges spread), its white variance ``c / S``, its
    gradient ``g = N[:3] / S`` (k, 3; about the near rays' line of sight, unit length) and
    ``m2 = sum_p |N_p[:3]|^2 / S^2`` (``-N_p[:3] . b / S`` is what an error ``b`` shared by
    pass ``p``'s rays does to ``delta``; ``m2 = |g|^2 / n`` for ``n`` passes alike).
    ``c`` is the rays' white noise measured over the claimed: their weighted squared
    residuals about their passes' lines at ``x`` over the degrees of freedom, with
    :data:`NOISE_PRIOR_DOF` at 1 (vehicles that claim more box noise than their boxes
    have would otherwise hide a discrepancy; ones that claim less, flag right
    landmarks)."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    x = np.asarray(x, float).reshape(-1, 3)
    den = np.where(s[:, 4] > 0, s[:, 4], np.nan)
    g = s[:, :3] / den[:, None]
    delta = np.einsum("ki,ki->k", g, x) + s[:, 3] / den
    xx = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    rss = np.maximum(np.einsum("ki,kij,kj->k", xx, _sym(s[:, 6:16]), xx), 0.0)
    c = (rss + NOISE_PRIOR_DOF) / (s[:, 16] + NOISE_PRIOR_DOF)
    return delta, c / den, g, s[:, 5] / den**2


def shared_scatter(sums: ArrayLike, x: ArrayLike) -> tuple[Array, Array]:
    """(q, a) (k,) at trial points ``x``: with pass ``p``'s own slope ``delta_p`` (white
    variance ``c / S_p``, shared ``tau^2 |N_p|^2 / S_p^2``), ``q = sum_p S_p (delta_p -
    delta)^2 - c (P - 1)`` has expectation ``tau^2 a``, ``a = sum_p |N_p|^2 / S_p - sum_p
    |N_p|^2 / S`` (NaN for sums of an older layout)."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    x = np.asarray(x, float).reshape(-1, 3)
    return _scatter(s, x, *offset(s, x)[:2])


def _scatter(s: Array, x: Array, delta: Array, var: Array) -> tuple[Array, Array]:
    """:func:`shared_scatter` from :func:`offset`'s ``delta`` and ``var`` at ``x``."""
    xx = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    den = np.where(s[:, 4] > 0, s[:, 4], np.nan)
    q = np.einsum("ki,kij,kj->k", xx, _sym(s[:, 17:27]), xx) - den * delta**2
    q = q - var * den * np.maximum(s[:, 28] - 1.0, 0.0)
    return q, s[:, 27] - s[:, 5] / den


def _tau2(s: Array, q: Array, a: Array, prior_m: float) -> Array:
    """``q / a`` with :data:`SHARED_PRIOR_PASSES` at ``prior_m`` (of the same ``a`` per
    pass); ``prior_m^2`` where there is no measure."""
    with np.errstate(divide="ignore", invalid="ignore"):
        w0 = SHARED_PRIOR_PASSES * a / s[:, 28]
        tau2 = (q + w0 * prior_m**2) / (a + w0)
    return np.where(np.isfinite(tau2) & (a > 0), np.maximum(tau2, 0.0), prior_m**2)


def shared_error(sums: ArrayLike, x: ArrayLike, prior_m: float) -> Array:
    """``tau^2`` (k,): the passes' shared position error per axis, m^2, as their own slopes
    at ``x`` scatter about the pooled one (:func:`shared_scatter`'s ``q / a``), with
    :data:`SHARED_PRIOR_PASSES` at ``prior_m``. Sums without these terms (an older layout,
    NaN) give ``prior_m^2``.

    Pitfall: a landmark holding two panels' rays (a mixture) has passes whose slopes
    disagree; its ``tau`` grows and its check weakens. On the evaluation's seed 0 (main
    of 2299e31) its three mixtures had ``tau`` 2.3, 5.1 (phones) and 3.1 m (simulated
    receiver) against the paired landmarks' 99th percentile of 4.0 and 5.0 m: ``tau``
    does not tell a mixture apart either."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    return _tau2(s, *shared_scatter(s, x), prior_m)


def discrepancy(
    sums: ArrayLike, x: ArrayLike, cov: ArrayLike, tau_m: float
) -> tuple[Array, Array, Array]:
    """(t, g, spread): ``t = delta / sqrt(spread)``, ``spread = c / S + tau^2 m2 + g^T C
    g`` (:func:`offset`: the rays' white part, what the passes' shared position errors,
    ``tau`` per axis as their slopes measure it (:func:`shared_error`, ``tau_m`` its
    prior), do to the slope, and what the estimate's covariance ``C`` (k x 3 x 3) lets
    ``delta`` move). With one panel at the estimate's place up to ``C``, ``t`` is about
    standard normal; NaN where no pass's inverse ranges spread. Where it is too large,
    :func:`hdmap.mapping.box_ranges.widened_along` with ``g`` and ``spread``."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    x = np.asarray(x, float).reshape(-1, 3)
    delta, var, g, m2 = offset(s, x)
    c = np.asarray(cov, float).reshape(-1, 3, 3)
    tau2 = _tau2(s, *_scatter(s, x, delta, var), tau_m)
    spread = var + tau2 * m2 + np.einsum("ki,kij,kj->k", g, c, g)
    with np.errstate(invalid="ignore"):
        t = delta / np.sqrt(spread)
    return t, g, spread
