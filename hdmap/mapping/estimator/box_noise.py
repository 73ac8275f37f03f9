"""The box ranges' white noise measured from the passes themselves (``range_scale="inverse"``).

In the inverse-range form (:func:`~hdmap.mapping.estimator.terms.inverse_range_terms`) a
ray's box gives ``rho = 1 / r``, Gaussian about ``1 / (s r_t)`` with the panel's unknown
scale ``s`` shared by the pass, and each pass adds ``rho_j d_j . (x - a_j) = s``. The
square ``rho^2`` in the normal equations is biased by ``sigma_rho^2`` (``E[rho^2] =
rho_t^2 + sigma_rho^2``), and that bias is not small: the distance along the line of sight
is the small difference between ``A_xx`` and ``A_xs A_xs^T / A_ss``, so a
``sigma_rho^2`` wrong by the whole pixel noise moves a head-on landmark 2 m or more
(docs/experiments/2026-12-per-pass-range-scale.md). What the vehicle claims for its boxes
cannot be trusted that far (the simulator's judged noise claims 4.24 px on boxes that have
none), so the noise is measured.

**The measurement.** Per pass, with the landmark's reference position ``x_ref``, ``D_j =
d_j . (x_ref - a_j)`` and ``u_j = rho_j D_j``: for exact boxes ``rho_j = 1 / (s (D_j - d_j
. e))``, ``e = x_ref - x_t`` the reference's error, so ``u_j = 1 / s + (d_j / D_j) . e / s``
to first order: linear in the regressors ``z_j = (1, d_j / D_j)``, which hold no box noise
(``rho_j d_j`` would: fitted on it, the noise explains itself and the measured ratio came
out at two thirds of the truth). So ``u_j`` is fitted on ``z_j`` (four coefficients) by
weighted least squares, weights ``1 / (D_j^2 sigma_rho,j^2)`` from the vehicle's claim, and
the weighted residual sum over the landmark's passes, divided by its degrees of freedom
(``n_p`` minus the fit's rank per pass), estimates the ratio ``c`` of the true noise
variance to the claimed one: the claim sets the shape (which rays are noisier), the data
its level. The reference's error does not enter the residuals to first order (a fit of
``1 / s`` and the error along the line of sight alone measured 1.45 times the true noise
with the reference 5 m off). A pass's shared origin error is such an error too; the rays'
white origin noise is not: it adds ``rho^2 d^T Sigma_a d`` per ray to ``u``'s variance,
which does not bias ``rho^2``, so its claimed share is taken out of the residuals before
they are pooled (in the fleet evaluation, 1 m of white origin noise is worth 0.1-0.2 of a
4.24 px claim, and counted as box noise it put the landmarks 0.3-0.6 m beyond their
signs). The fit needs 17 sums per open pass
(:data:`FIT`: ``sum w z z^T``, ``sum w z u``, ``sum w u^2``, the ray count), and a pass's
residual sum and degrees of freedom once it is settled (:func:`pass_residuals`); the
landmark pools them. ``c`` is shrunk toward the claim (1) by ``prior_dof`` pseudo degrees
of freedom, so a landmark with one short pass compensates as claimed.

**The compensation** ``c sigma_rho^2`` is applied when a pass enters the landmark's sums
(closing it, or in ``solve`` for the open ones), with the ``c`` pooled from every pass so
far, the entering ones included: each open pass keeps its compensation sums apart
(:data:`COMP`: ``sum w sigma_rho^2 D~`` and the same times the origin, 9 floats).

Invariants and pitfalls:

- ``c`` changes as passes arrive, so a closed pass keeps the ``c`` it entered with: the
  result depends on the order passes close (deterministic for a given log, so replays are
  exact), unlike the rest of the sums (open_passes's "a result never depends on when a
  pass is closed" holds only with box ranges off or in the other modes).
- ``u`` uses the reference as it was when the ray arrived; a reference moved in the middle
  of a pass changes ``e`` within it, which the fit does not absorb (the matcher and the
  solver move it between units, rarely inside one pass's rays).
- Two passes folded into one (a merge of two landmarks that one pass saw) are settled
  first (:func:`settle`): their fits were about different references.

>>> k = np.zeros((1, WIDTH))
>>> rho = np.array([0.02, 0.025, 0.03, 0.04, 0.05, 0.07])
>>> d = np.column_stack([3 * rho, np.ones(6), 0.5 * rho])
>>> d /= np.linalg.norm(d, axis=1, keepdims=True)
>>> e = np.array([1.0, -2.0, 0.3])  # the reference's error
>>> u = 1.0 + rho * (d @ e) + 0.01 * np.array([1, -1, 1, -1, 1, -1])
>>> k[0, FIT] = fit_sums(np.ones(6), rho, d, u, np.zeros(6)).sum(0)
>>> rss, dof = pass_residuals(k)
>>> dof.tolist(), bool(0 < rss[0] < 6e-4)  # d_E, d_U in proportion: rank 3
([3.0], True)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from hdmap.mapping.estimator.frame_change import FrameChange

Array = NDArray[np.float64]

COMP = slice(0, 9)
"""Columns of an open pass's compensation sums: ``sum w sigma_rho^2 D~`` (6, the symmetric
3x3 as a 6-vector) and ``sum w sigma_rho^2 D~ a`` (3)."""
FIT = slice(9, 26)
"""Columns of its fit sums: ``sum w z z^T`` (10, upper triangle of the 4x4, row-major),
``sum w z u`` (4), ``sum w u^2``, the ray count and ``sum w v_pos``, the claimed white
origin noise's variance in ``u`` (:func:`pass_residuals` takes its share out)."""
SETTLED = slice(26, 28)
"""Columns of its settled residual sum and degrees of freedom (:func:`settle`)."""
WIDTH = 28
"""Floats per open pass."""

_TRI_I, _TRI_J = np.triu_indices(4)
_RANK_TOL = 1e-9
"""Eigenvalues of the fit's scaled normal matrix below this (relative to its largest) are
directions the pass's rays do not determine: not fitted, no degree of freedom taken."""


def fit_sums(w: Array, q: Array, d: Array, u: Array, v_pos: Array) -> Array:
    """Per ray its terms of the pass fit ``u ~ z . beta``, ``z = (1, q d)`` (weights
    ``w``; rays with ``w`` 0 count nothing; ``q = 1 / D`` in the services; ``v_pos`` the
    variance the ray's white origin noise adds to ``u``): (n, 17), the :data:`FIT`
    columns."""
    z = np.column_stack([np.ones_like(q), q[:, None] * np.asarray(d, float)])
    out = np.empty((w.size, 17))
    out[:, :10] = w[:, None] * z[:, _TRI_I] * z[:, _TRI_J]
    out[:, 10:14] = (w * u)[:, None] * z
    out[:, 14] = w * u**2
    out[:, 15] = (w > 0).astype(float)
    out[:, 16] = w * v_pos
    return out


def pass_residuals(k: Array) -> tuple[Array, Array]:
    """Weighted residual sum and degrees of freedom of passes' sums ``k`` (..., WIDTH): the
    fit's (``n`` minus its rank; 0 and 0 where the rays are no more than the rank), less
    the claimed white origin noise's share (``sum w v_pos`` times ``dof / n``, the average
    ``1 - h_jj``; so it can be negative), plus the settled part."""
    k = np.asarray(k, float)
    f = k[..., FIT].reshape(-1, 17)
    s = np.zeros((f.shape[0], 4, 4))
    s[:, _TRI_I, _TRI_J] = f[:, :10]
    s[:, _TRI_J, _TRI_I] = f[:, :10]
    t, uu, n = f[:, 10:14], f[:, 14], f[:, 15]
    diag = np.sqrt(np.maximum(np.einsum("kii->ki", s), 1e-300))
    sn = s / (diag[:, :, None] * diag[:, None, :])
    lam, vec = np.linalg.eigh(sn)
    keep = lam > _RANK_TOL * np.maximum(lam[:, -1:], 1e-300)
    proj = np.einsum("kij,ki->kj", vec, t / diag)  # t in the scaled eigenbasis
    explained = np.sum(np.where(keep, proj**2 / np.where(keep, lam, 1.0), 0.0), axis=1)
    rank = keep.sum(axis=1)
    good = n > rank
    dof = np.where(good, n - rank, 0.0)
    share = f[:, 16] * dof / np.maximum(n, 1.0)
    rss = np.where(good, np.maximum(uu - explained, 0.0) - share, 0.0)
    shape = k.shape[:-1]
    return (
        rss.reshape(shape) + k[..., SETTLED.start],
        dof.reshape(shape) + k[..., SETTLED.start + 1],
    )


def settle(k: Array) -> Array:
    """Passes' sums with the fit turned into its residual sum and degrees of freedom."""
    out = np.array(k, float, copy=True)
    rss, dof = pass_residuals(k)
    out[..., FIT] = 0.0
    out[..., SETTLED.start], out[..., SETTLED.start + 1] = rss, dof
    return out


def in_frame(k: Array, frame: FrameChange) -> Array:
    """An open pass's sums ``k`` (WIDTH,) seen from another row's frame (a
    :class:`~hdmap.mapping.estimator.frame_change.FrameChange`): the compensation moves
    like ``A`` and ``b``; the fit is about scalars and stays. Without the inverse form a
    pass keeps no such sums (``k`` empty): returned as it is."""
    out = np.array(k, float, copy=True)
    if out.size == 0:
        return out
    a6, b = frame.terms(out[COMP.start : COMP.start + 6], out[COMP.start + 6 : COMP.stop])
    out[COMP.start : COMP.start + 6], out[COMP.start + 6 : COMP.stop] = a6, b
    return out


def noise_ratio(rss: Array, dof: Array, prior_dof: float) -> Array:
    """The ratio ``c`` of the boxes' true inverse-range noise variance to the claimed one,
    from pooled residuals, shrunk toward 1 by ``prior_dof`` pseudo degrees of freedom.

    >>> rss, dof = np.array([0.0, 50.0, 0.0]), np.array([0.0, 100.0, 1000.0])
    >>> noise_ratio(rss, dof, 4.0).round(4).tolist()
    [1.0, 0.5192, 0.004]
    """
    rss = np.maximum(np.asarray(rss, float), 0.0)
    return (rss + prior_dof) / (np.asarray(dof, float) + prior_dof)
