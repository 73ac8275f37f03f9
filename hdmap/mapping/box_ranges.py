"""Box ranges as evidence of which panel a landmark's rays saw: O(1) sums per landmark
that give its rays' mean relative range at any trial point.

A ray with a box range ``r`` (from the box's height and the class's nominal panel height)
from origin ``a`` along unit direction ``d`` says the panel is about ``r`` away. At a
trial point ``x`` its **relative range** is ``u(x) = d . (x - a) / r``: the distance
along the ray to ``x`` over the measured range. At the panel's real position every ray of
the panel has ``u = s`` up to its box's pixel noise and its origin's error, ``s`` the
panel's real size over its class's nominal size: one unknown for all the panel's rays
(10 % spread by default), so two landmarks made of one panel's rays have the same mean
``u`` at that panel, and two panels' landmarks each their own.

State: ``h = (d / r, -(d . a) / r, 1)`` per ray, so that ``u(x) = h[:4] . (x, 1)``; a
landmark keeps ``sum_j w_j h_j`` (5 numbers) in its home tile's frame, and its mean
relative range at ``x`` is ``sum w u / sum w``. Sums add when landmarks merge; a rigid
change of frame ``x' = R x + t`` maps ``h`` linearly (:func:`in_frame`), since ``u`` does
not depend on the frame.

Weights: ``w = 1 / (rel_w^2 + (sigma_h / r)^2)``, ``rel_w^2`` the box's own relative
range variance (what the vehicle reports, ``(sigma_r / r)^2``, less the catalogue's panel
spread every ray of the panel shares; at least ``REL_FLOOR^2``) and ``sigma_h`` the
origin's horizontal GNSS sigma (a metre of origin error moves ``u`` of a ray at ``r`` by
``1 / r``). Rays without a range (``r <= 0``, NaN) add nothing.

Used by the merge test of a sign's second landmark made of its rays from another street
(:func:`hdmap.mapping.merge.ghost_partner`; docs/experiments/2026-12-two-street-ghosts-
ranges.md): those rays' mean relative range at the sign's landmark equals the sign's own
rays' there (one panel), and differs at their own landmark several metres along their
line of sight. Pitfall: the sums keep the rays of a vehicle on probation whose links
are later dropped (as the view sums do); the mean moves by their share.

>>> import numpy as np
>>> a = np.array([[0.0, -30.0, 0.0], [0.0, -20.0, 0.0], [0.0, -10.0, 0.0]])
>>> d = np.tile([0.0, 1.0, 0.0], (3, 1))  # looking North at a panel at the origin
>>> r = np.array([30.0, 20.0, 10.0]) / 0.9  # a panel 0.9 of the nominal size
>>> h, w = ray_terms(a, d, r, r * 0.1, 0.5, 0.1)
>>> s = summed(np.zeros(3, np.int64), h, w)
>>> round(float(mean_relative_range(s, np.zeros((1, 3)))[0]), 4)  # at the panel
0.9
>>> round(float(mean_relative_range(s, np.array([[0.0, 5.0, 0.0]]))[0]), 4)  # 5 m beyond
1.1163
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping.estimator.terms import white_rel_var

Array = NDArray[np.float64]

N_SUMS = 5
"""Numbers a landmark keeps: ``sum w h``."""

REL_FLOOR = 0.02
"""Smallest relative white range sigma a ray's weight assumes (a box a pixel or two off
at 60-100 px)."""


def ray_terms(
    origin: ArrayLike,
    direction: ArrayLike,
    range_m: ArrayLike,
    sigma_range_m: ArrayLike,
    sigma_pos_h: ArrayLike,
    panel_rel_sigma: float,
) -> tuple[Array, Array]:
    """Per ray ``h`` (n, 5) and weight ``w`` (n,) (0 where the ray has no range)."""
    a = np.asarray(origin, float).reshape(-1, 3)
    d = np.asarray(direction, float).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    use, rs, rel_w2 = white_rel_var(range_m, sigma_range_m, panel_rel_sigma, REL_FLOOR)
    s_h = np.asarray(sigma_pos_h, float) * np.ones(rs.size)
    w = np.where(use, 1.0 / (rel_w2 + (s_h / rs) ** 2), 0.0)
    h = np.empty((rs.size, 5))
    h[:, :3] = d / rs[:, None]
    h[:, 3] = -np.einsum("ij,ij->i", d, a) / rs
    h[:, 4] = 1.0
    return h, w


def summed(group: ArrayLike, h: Array, w: Array) -> Array:
    """Rays summed by the landmark each went to (``group``: 0, 1, ... per ray): (k,
    ``N_SUMS``), ``k`` the number of groups."""
    g = np.asarray(group, np.int64).reshape(-1)
    out = np.zeros((int(g.max(initial=-1)) + 1, N_SUMS))
    np.add.at(out, g, w[:, None] * h)
    return out


def in_frame(sums: ArrayLike, rot: Array | None, t: Array | None) -> Array:
    """Sums kept in frame F as they are in frame G, ``x_G = rot x_F + t``
    (:func:`hdmap.geo.tiles.frame_map`; None, None: the same frame)."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    if rot is None or t is None:
        return s.copy()
    lin = np.eye(5)
    lin[:3, :3] = rot
    lin[3, :3] = -(np.asarray(t, float) @ rot)
    return s @ lin.T


def mean_relative_range(sums: ArrayLike, x: ArrayLike) -> Array:
    """At trial points ``x`` (k, 3; point ``i`` for landmark ``i``, in the sums' frame) the
    weighted mean relative range of each landmark's rays (k,); NaN where it has no ranged
    ray."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    x = np.asarray(x, float).reshape(-1, 3)
    w = s[:, 4]
    su = np.einsum("ki,ki->k", s[:, :3], x) + s[:, 3]
    return np.divide(su, w, out=np.full(w.size, np.nan), where=w > 0)


Z_CAP = 1e3
"""``|z|`` of a landmark whose rays' mean relative range is not positive (the estimate
behind its cameras as the ranges see it)."""


def panel_discrepancy(
    sums: ArrayLike, x: ArrayLike, cov: ArrayLike, panel_rel_sigma: float
) -> tuple[Array, Array, Array]:
    """(z, g, s): how far the landmarks' panels are, by their rays' box ranges, from where
    their estimates ``x`` (k, 3) are. ``s`` is the rays' mean relative range at ``x``
    (:func:`mean_relative_range`; the panel's size over its class's nominal size if
    ``x`` is right), ``g = ds/dx`` (k, 3) the weighted mean of the rays' ``d / r`` (along
    the mean line of sight, ``1 / r`` long at a typical range ``r``), and ``z = ln s /
    sqrt(panel_rel_sigma^2 + g^T C g / s^2)``: the catalogue's log-normal size spread and
    what the position's covariance ``C`` (``cov``, k x 3 x 3, the sums' frame) lets ``ln
    s`` move. With one panel whose size is log-normal with ``panel_rel_sigma`` and ``x``
    where ``C`` says, ``z`` is standard normal up to the rays' white noise; NaN where no
    ray has a range, ``-Z_CAP`` where ``s <= 0``.

    >>> a = np.array([[0.0, -40.0, 0.0], [0.0, -30.0, 0.0], [0.0, -20.0, 0.0]])
    >>> d = np.tile([0.0, 1.0, 0.0], (3, 1))  # looking North at a nominal panel at 0
    >>> r = np.array([40.0, 30.0, 20.0])
    >>> sums = summed(np.zeros(3, np.int64), *ray_terms(a, d, r, r * 0.1, 0.5, 0.1))
    >>> z, g, s = panel_discrepancy(sums, np.array([[0.0, 12.0, 0.0]]), np.eye(3)[None], 0.1)
    >>> round(float(z[0]), 2), g.round(3).tolist(), s.round(3).tolist()  # 12 m beyond
    (3.3, [[0.0, 0.034, 0.0]], [1.404])
    """
    sm = np.asarray(sums, float).reshape(-1, N_SUMS)
    c = np.asarray(cov, float).reshape(-1, 3, 3)
    w = sm[:, 4]
    s = mean_relative_range(sm, x)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(w[:, None] > 0, sm[:, :3] / w[:, None], np.nan)
        spread = panel_rel_sigma**2 + np.einsum("ki,kij,kj->k", g, c, g) / s**2
        z = np.where(s > 0, np.log(s) / np.sqrt(spread), -Z_CAP)
    return np.where(np.isnan(s), np.nan, z), g, s


def widened_along(
    cov: ArrayLike, z: ArrayLike, grad: ArrayLike, spread: ArrayLike, k: float
) -> Array:
    """``cov`` (k x 3 x 3) where ``|z| > k`` widened along ``grad`` until ``|z| = 1``, for a
    statistic ``z = q / sqrt(spread)`` whose numerator ``q`` has gradient ``grad`` with
    respect to the position and ``spread`` includes ``grad^T cov grad``: what the
    discrepancy leaves of the position along ``grad``. Elsewhere (and NaN ``z``)
    unchanged.

    >>> c = widened_along(np.eye(3)[None], np.array([5.0]), np.array([[0.0, 1.0, 0.0]]),
    ...                   np.array([2.0]), 3.0)
    >>> c.round(3).tolist()  # q^2 = 25 * 2 = 50: the spread grows by 48 along North
    [[[1.0, 0.0, 0.0], [0.0, 49.0, 0.0], [0.0, 0.0, 1.0]]]
    """
    c = np.array(cov, float).reshape(-1, 3, 3)
    zz = np.clip(np.asarray(z, float).reshape(-1), -Z_CAP, Z_CAP)
    bad = np.flatnonzero(np.abs(np.nan_to_num(zz)) > k)
    if bad.size:
        gb = np.asarray(grad, float).reshape(-1, 3)[bad]
        g2 = np.einsum("ki,ki->k", gb, gb)
        add = (zz[bad] ** 2 - 1.0) * np.asarray(spread, float).reshape(-1)[bad] / g2**2
        c[bad] += add[:, None, None] * gb[:, :, None] * gb[:, None, :]
    return c


def widened_along_sight(
    cov: ArrayLike, z: ArrayLike, g: ArrayLike, s: ArrayLike, k: float, panel_rel_sigma: float
) -> Array:
    """``cov`` (k x 3 x 3) where ``|z| > k`` (:func:`panel_discrepancy`'s ``z, g, s``)
    widened along ``g`` until the discrepancy is one standard deviation
    (:func:`widened_along` with ``ln s``'s gradient ``g / s``): what the box ranges leave
    of the estimate's distance along the line of sight. Elsewhere (and NaN ``z``)
    unchanged.

    >>> c = widened_along_sight(np.eye(3)[None], np.array([4.0]), np.array([[0.0, 0.1, 0.0]]),
    ...                         np.array([1.0]), 3.0, 0.1)
    >>> c.round(3).tolist()  # ln-s spread 0.02 -> 16 * 0.02: 0.3 more, 30 m^2 along North
    [[[1.0, 0.0, 0.0], [0.0, 31.0, 0.0], [0.0, 0.0, 1.0]]]
    """
    c = np.asarray(cov, float).reshape(-1, 3, 3)
    grad = (
        np.asarray(g, float).reshape(-1, 3)
        / np.maximum(np.asarray(s, float).reshape(-1), 1.0 / Z_CAP)[:, None]
    )
    spread = panel_rel_sigma**2 + np.einsum("ki,kij,kj->k", grad, c, grad)
    return widened_along(c, z, grad, spread, k)


def panel_update(
    sums: ArrayLike, x: ArrayLike, cov: ArrayLike, panel_rel_sigma: float, iterations: int = 3
) -> tuple[Array, Array, Array]:
    """(x', cov', z): the estimates ``x`` (k, 3) and covariances ``cov`` (k, 3, 3) updated
    with the catalogue's panel size as one measurement per landmark, ``ln s(x) = 0 +-
    panel_rel_sigma`` (its rays' mean relative range at the panel is its size over the
    nominal one): an iterated Kalman update along ``g`` (:func:`panel_discrepancy`), so
    the panel's size error counts once for all of a landmark's rays, not once per ray. A
    landmark located well by its bearings hardly moves (gain ``g^T C g / s^2`` over that
    plus ``panel_rel_sigma^2``); one whose distance along the line of sight they fix
    poorly takes it from the ranges. ``z`` is :func:`panel_discrepancy`'s at ``x``.
    Unchanged where no ray has a range or ``s(x) <= 0``.

    >>> a = np.array([[0.0, -40.0, 0.0], [0.0, -30.0, 0.0], [0.0, -20.0, 0.0]])
    >>> d = np.tile([0.0, 1.0, 0.0], (3, 1))  # looking North at a nominal panel at 0
    >>> r = np.array([40.0, 30.0, 20.0])
    >>> sums = summed(np.zeros(3, np.int64), *ray_terms(a, d, r, r * 0.1, 0.5, 0.1))
    >>> c = np.diag([0.1, 25.0, 0.1])[None]  # 5 m along the line of sight
    >>> x, c2, z = panel_update(sums, np.array([[0.0, 12.0, 0.0]]), c, 0.1)
    >>> x.round(2).tolist(), round(float(np.sqrt(c2[0, 1, 1])), 2), z.round(2).tolist()
    ([[0.0, 3.54, 0.0]], 2.77, [2.17])
    """
    x0 = np.asarray(x, float).reshape(-1, 3)
    c0 = np.asarray(cov, float).reshape(-1, 3, 3)
    z, g, s = panel_discrepancy(sums, x0, c0, panel_rel_sigma)
    ok = np.flatnonzero(np.isfinite(s) & (s > 0) & np.isfinite(x0).all(axis=1))
    xo, co = x0.copy(), c0.copy()
    if not ok.size:
        return xo, co, z
    sm = np.asarray(sums, float).reshape(-1, N_SUMS)[ok]
    gk, xb, cb = g[ok], x0[ok], c0[ok]
    xi = xb.copy()
    for _ in range(max(1, iterations)):
        si = np.maximum(mean_relative_range(sm, xi), 1e-6)
        hk = gk / si[:, None]  # d ln s / dx at xi
        ch = np.einsum("kij,kj->ki", cb, hk)
        gain = ch / (np.einsum("ki,ki->k", hk, ch) + panel_rel_sigma**2)[:, None]
        innov = -np.log(si) - np.einsum("ki,ki->k", hk, xb - xi)
        xi = xb + gain * innov[:, None]
    co[ok] = cb - gain[:, :, None] * ch[:, None, :]
    xo[ok] = xi
    return xo, co, z
