"""Per-ray normal-equation terms: the bearings' (bias-compensated, weighted; the model and
its derivation in :mod:`hdmap.mapping.estimator.model`) and the box ranges' (along the ray,
with the panel at its nominal size or with a per-pass unknown scale).

With zero angular noise the compensated and textbook terms coincide:

>>> r = Rays.from_angles(np.zeros((1, 3)), [0.3], [0.1], 0.0, 0.0, 1.0, 1.0)
>>> ref = np.array([[3.0, 10.0, 1.0]])
>>> a_c, _ = ray_terms(r, r.origin, ref, EstimatorConfig())
>>> a_t, _ = ray_terms(r, r.origin, ref, EstimatorConfig(compensate=False))
>>> bool(np.allclose(a_c, a_t))
True
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping.estimator.box_noise import COMP, FIT, WIDTH, fit_sums
from hdmap.mapping.estimator.model import (
    EstimatorConfig,
    Rays,
    effective_sigmas,
    mat_to_sym,
    projector_terms,
    ray_angles,
    row_dot,
    row_matvec,
    sym_to_mat,
    weights,
)

Array = NDArray[np.float64]

_I6 = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])


def range_terms(rays: Rays) -> Array:
    """Per ray the weight ``w_r`` of its box range as a constraint along the ray,
    ``d . (x - a) = r``: ``w_r D (x - a) = w_r d r`` joins the normal equations (``D`` the
    compensated ``d d^T``, ``I - m``), ``w_r = 1 / (sigma_r^2 + sigma_h^2)`` times the
    ray's weight, 0 where the ray has no range.

    Why: bearings alone hardly fix the distance of a sign a car sees head-on down a street
    (nearly parallel rays), and a pass's shared heading error moves it far along the line
    of sight (one such sign from its true rays: 39 m off by least squares on bearings,
    1.5 m with the ranges; docs/experiments/2026-12-ghosts-at-high-traffic.md). The range
    is along the measured direction, so the term is linear in ``x``; ``E[d] = d_t (1 -
    O(s^2))`` leaves a bias of ``r s^2 / 2`` (2 mm at 40 m and 0.01 rad).

    Pitfall: a panel's real size differs from its class's nominal height, an error every
    ray of that landmark shares (``size_rel_sigma`` in the sign catalogue, in each ray's
    ``sigma_range_m``). These terms treat it as independent per ray; the published
    covariance keeps its model floor from the bearings' predicted information
    (:func:`predicted_information` has no range term), so it does not shrink along the
    line of sight on the ranges' account."""
    r = np.asarray(rays.range_m, float).reshape(-1)
    sr = np.asarray(rays.sigma_range_m, float).reshape(-1)
    s_h = np.asarray(rays.sigma_pos_h, float) * np.ones(r.size)
    use = (r > 0) & (sr > 0) & np.isfinite(r) & np.isfinite(sr)
    w = np.where(use, 1.0 / np.where(use, sr**2 + s_h**2, 1.0), 0.0)
    return w * rays.weights_or_ones()


class InverseTerms(NamedTuple):
    """Per ray of the inverse-range form: weight, inverse range, claimed white variance
    (:func:`inverse_range_terms`; computed once per ``accumulate`` and shared by
    :func:`ray_terms`, :func:`scale_terms` and :func:`noise_terms`)."""

    w: Array
    rho: Array
    s_rho2: Array


def white_rel_var(
    range_m: ArrayLike, sigma_range_m: ArrayLike, panel_rel_sigma: float, floor: float
) -> tuple[NDArray[np.bool_], Array, Array]:
    """Per ray: whether it has a range, its range (1 where none) and the white part of its
    relative range variance, ``(sigma_r / r)^2 - panel_rel_sigma^2`` (the vehicle sends
    the box's white part and the catalogue's panel spread summed), at least ``floor^2``."""
    r = np.asarray(range_m, float).reshape(-1)
    sr = np.asarray(sigma_range_m, float).reshape(-1)
    use = (r > 0) & (sr > 0) & np.isfinite(r) & np.isfinite(sr)
    rs = np.where(use, r, 1.0)
    return use, rs, np.maximum((np.where(use, sr, 0.0) / rs) ** 2 - panel_rel_sigma**2, floor**2)


def inverse_range_terms(
    rays: Rays, origin_rel: Array, x_ref_rel: Array, cfg: EstimatorConfig
) -> InverseTerms:
    """Per ray of the inverse-range form (``range_scale="inverse"``), ``rho d . (x - a) =
    s``: its weight ``w``, inverse range ``rho = 1 / r`` and claimed white variance
    ``sigma_rho^2`` (0 and 0 where the ray has no range).

    ``sigma_rho = rel_w / r`` with ``rel_w^2 = (sigma_r / r)^2 - panel_rel_sigma^2`` (the
    vehicle sends the box's white part and the catalogue's panel spread summed; the panel's
    scale is the pass's ``s`` here, so only the white part is noise), floored at 1 %. For a
    box of ``h`` px, ``rel_w = sqrt(2) sigma_px / h`` grows as ``r``, so ``sigma_rho`` is
    about the same for every ray of one camera and class: free of the measured box, as the
    compensation needs. ``w = 1 / (sigma_rho^2 r_ref^2 + sigma_h^2 / r_ref^2)`` with the
    range ``r_ref`` to the reference position (never the ray's own), times the ray weight.
    """
    use, rs, rel_w2 = white_rel_var(rays.range_m, rays.sigma_range_m, cfg.panel_rel_sigma, 0.01)
    s_rho2 = np.where(use, rel_w2 / rs**2, 0.0)
    v = x_ref_rel - origin_rel
    r_ref2 = np.maximum(row_dot(v, v), cfg.min_range_m**2)
    s_h2 = np.maximum(np.asarray(rays.sigma_pos_h, float), cfg.min_sigma_pos_m) ** 2
    w = np.where(use, 1.0 / (s_rho2 * r_ref2 + s_h2 / r_ref2), 0.0) * rays.weights_or_ones()
    return InverseTerms(w, np.where(use, 1.0 / rs, 0.0), s_rho2)


def inverse_of(
    rays: Rays, origin_rel: Array, x_ref_rel: Array | None, cfg: EstimatorConfig
) -> InverseTerms | None:
    """The rays' :class:`InverseTerms` in the inverse-range form (None otherwise)."""
    if not (cfg.box_range and cfg.range_scale == "inverse") or rays.range_m is None:
        return None
    if x_ref_rel is None:
        raise ValueError("the inverse-range form needs the reference positions")
    return inverse_range_terms(rays, origin_rel, x_ref_rel, cfg)


def noise_terms(
    rays: Rays,
    origin_rel: Array,
    x_ref_rel: Array,
    cfg: EstimatorConfig,
    inv: InverseTerms | None = None,
) -> Array | None:
    """Per ray (n, WIDTH) its compensation sums and its terms of the pass's box-noise fit
    (:mod:`hdmap.mapping.estimator.box_noise`: ``w sigma_rho^2 D~``, the same times the
    origin, and :func:`~hdmap.mapping.estimator.box_noise.fit_sums` of ``u = rho D``, ``D =
    d . (x_ref - a)``, weights ``1 / (D^2 sigma_rho^2)``); None unless
    ``range_scale="inverse"`` with box ranges. ``inv``: the rays' :func:`inverse_of`, if
    already at hand."""
    inv = inv or inverse_of(rays, origin_rel, x_ref_rel, cfg)
    if inv is None:
        return None
    w, rho, s_rho2 = inv
    az, el = ray_angles(rays.direction)
    s_az, s_el = effective_sigmas(rays, cfg)
    m, _h = projector_terms(az, el, s_az, s_el, cfg.compensate)
    out = np.zeros((len(rays), WIDTH))
    comp = (w * s_rho2)[:, None] * (_I6 - m)
    out[:, COMP.start : COMP.start + 6] = comp
    out[:, COMP.start + 6 : COMP.stop] = row_matvec(sym_to_mat(comp), origin_rel)
    d = np.asarray(rays.direction, float)
    dist = row_dot(d, x_ref_rel - origin_rel)
    ok = (s_rho2 > 0) & (dist > cfg.min_range_m)
    wf = np.where(ok, 1.0 / np.where(ok, dist**2 * s_rho2, 1.0), 0.0)
    inv_dist = np.divide(1.0, dist, out=np.zeros_like(dist), where=ok)
    s_h2 = np.maximum(np.asarray(rays.sigma_pos_h, float), cfg.min_sigma_pos_m) ** 2
    s_v2 = np.maximum(np.asarray(rays.sigma_pos_v, float), cfg.min_sigma_pos_m) ** 2
    v_pos = rho**2 * (s_h2 * (d[:, 0] ** 2 + d[:, 1] ** 2) + s_v2 * d[:, 2] ** 2)
    out[:, FIT] = fit_sums(wf, inv_dist, d, np.where(ok, rho * dist, 0.0), v_pos)
    return out


def scale_terms(
    rays: Rays,
    origin_rel: Array,
    cfg: EstimatorConfig,
    x_ref_rel: Array | None = None,
    inv: InverseTerms | None = None,
) -> Array | None:
    """Per ray its terms in a pass's unknown range scale ``s`` (``range_scale="per_pass"``):
    (n, 5) columns ``A_xs`` (3), ``A_ss``, ``b_s`` with, over the pass's rays,

        [[A_xx, A_xs], [A_xs^T, A_ss]] [x; s] = [b_x; b_s],
        A_xs = -sum w_r r d,   A_ss = sum w_r r^2,   b_s = -sum w_r r d . a

    (``A_xx``, ``b_x`` hold ``w_r D`` and ``w_r D a`` from :func:`ray_terms`). A pass enters
    the landmark with ``s`` eliminated (Schur complement, :func:`eliminate_scale`):
    ``A_xx - A_xs A_xs^T / A_ss``. One ranged ray then adds nothing along its line of
    sight; two or more fix the distance by how their ranges differ as the origin moves
    (``d . (a_j - a_i) = s (r_i - r_j)``), a pass's shared position error cancelling.
    None when no ray has a range or the mode is off. In the inverse form
    (``range_scale="inverse"``, ``rho d . (x - a) = s``; needs ``x_ref_rel``) the same
    columns are ``-sum w rho d``, ``sum w``, ``-sum w rho d . a``
    (:func:`inverse_range_terms`; ``inv`` if already at hand).

    >>> r = Rays.from_angles([[0.0, 0, 0], [0, 5, 0]], [0.0, 0.0], [0.0, 0.0], 0.0, 0.0, 0.1, 0.1)
    >>> from dataclasses import replace
    >>> r = replace(r, range_m=np.array([15.0, 10.0]), sigma_range_m=np.array([0.5, 0.5]))
    >>> cfg = EstimatorConfig(box_range=True)
    >>> a6, b = ray_terms(r, r.origin, np.array([[0.0, 15, 0]] * 2), cfg)
    >>> t = scale_terms(r, r.origin, cfg).sum(axis=0)
    >>> a6, b = eliminate_scale(a6.sum(axis=0), b.sum(axis=0), t)
    >>> round(float(b[1] / a6[1]), 6)  # the sign 15 m ahead, whatever the panel size
    15.0
    """
    if not (cfg.box_range and cfg.range_scale != "nominal") or rays.range_m is None:
        return None
    if cfg.range_scale == "inverse":  # rho d . (x - a) = s: d's coefficient w rho, s's w
        w, rho, _ = inv or inverse_of(rays, origin_rel, x_ref_rel, cfg)
        c, ss = w * rho, w
    else:  # d . (x - a) = s r: d's coefficient w_r r, s's w_r r^2
        w_r = range_terms(rays)
        c = w_r * np.where(w_r > 0, np.asarray(rays.range_m, float), 0.0)
        ss = c * np.where(w_r > 0, np.asarray(rays.range_m, float), 0.0)
    d = np.asarray(rays.direction, float)
    out = np.empty((len(rays), 5))
    out[:, :3] = -c[:, None] * d
    out[:, 3] = ss
    out[:, 4] = -c * row_dot(d, origin_rel)
    return out


def eliminate_scale(a6: Array, b: Array, t: Array) -> tuple[Array, Array]:
    """Passes' sums ``(a6, b)`` (..., 6), (..., 3) with their range scale eliminated, from
    their :func:`scale_terms` sums ``t`` (..., 5): ``A - A_xs A_xs^T / A_ss``, ``b - A_xs
    b_s / A_ss`` (unchanged where ``A_ss`` is 0)."""
    xs, ss, bs = t[..., :3], t[..., 3], t[..., 4]
    if not np.any(ss > 0):  # no ranged pass (box ranges off): nothing to eliminate
        return a6.copy(), b.copy()
    inv = np.divide(1.0, ss, out=np.zeros_like(ss), where=ss > 0)
    a_out = a6 - inv[..., None] * mat_to_sym(xs[..., :, None] * xs[..., None, :])
    return a_out, b - (inv * bs)[..., None] * xs


def ray_terms(
    rays: Rays,
    origin_rel: Array,
    x_ref_rel: Array,
    cfg: EstimatorConfig,
    inv: InverseTerms | None = None,
    wts: tuple[Array, Array, Array, Array] | None = None,
) -> tuple[Array, Array]:
    """Per-ray normal-equation terms ``(alpha, beta)``: ``alpha`` (n, 6) is ``Q~_j`` as a
    6-vector and ``beta`` (n, 3) is ``Q~_j a_j`` (origins relative to the anchor).

    Pitfall: with ``box_range`` and ``range_scale="per_pass"`` or ``"inverse"`` these hold
    only the ``x`` block of the range terms; a pass's sums need its :func:`scale_terms`
    eliminated (:func:`eliminate_scale`), and in the inverse form its measured compensation
    (:func:`noise_terms`) taken off, before they mean anything (``LandmarkSums`` does both).

    ``sum alpha`` and ``sum beta`` are the landmark's ``A`` and ``b``; ``A x = b`` is the
    estimate. ``x_ref_rel`` is each ray's landmark reference position (for the weights);
    ``wts``: :func:`~hdmap.mapping.estimator.model.weights` of these arguments when the
    caller has them.
    """
    az, el = ray_angles(rays.direction)
    s_az, s_el = effective_sigmas(rays, cfg)
    m, h = projector_terms(az, el, s_az, s_el, cfg.compensate)
    w_h, w_v, g_h, g_v = wts or weights(rays, origin_rel, x_ref_rel, cfg)
    alpha = w_v[:, None] * m + (w_h - w_v)[:, None] * h
    w_r = range_terms(rays) if cfg.box_range and rays.range_m is not None else None
    if w_r is not None and cfg.range_scale == "inverse":
        # raw rho^2 here; the measured compensation is applied per pass (noise_terms)
        w_i, rho, _ = inv or inverse_of(rays, origin_rel, x_ref_rel, cfg)
        w_r = w_i * rho**2
    if w_r is not None:
        alpha = alpha + w_r[:, None] * (_I6 - m)
    beta = row_matvec(sym_to_mat(alpha), origin_rel)
    if w_r is not None and cfg.range_scale == "nominal":
        r = np.asarray(rays.range_m, float)
        beta = beta + (w_r * np.where(w_r > 0, r, 0.0))[:, None] * np.asarray(rays.direction)
    if cfg.weight_correction and cfg.weighting == "inverse_variance":
        sig = np.stack(
            [
                np.asarray(rays.sigma_pos_h, float) ** 2,
                np.asarray(rays.sigma_pos_h, float) ** 2,
                np.asarray(rays.sigma_pos_v, float) ** 2,
            ],
            axis=1,
        )
        corr = row_matvec(sym_to_mat(m - h), sig * g_v) + row_matvec(sym_to_mat(h), sig * g_h)
        beta = beta - corr
    return alpha, beta
