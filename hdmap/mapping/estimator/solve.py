"""Estimate, pass-level (cluster) sandwich covariance and conditioning, from fixed-size sums.

Per landmark, with ``A = sum_p A_p`` and ``b = sum_p b_p`` summed over passes ``p`` (each
``A_p``, ``b_p`` the sum of the pass's ray terms,
:func:`hdmap.mapping.estimator.terms.ray_terms`):

- estimate ``x^ = A^-1 b`` (the root of the unbiased estimating function
  ``G(x) = sum_p g_p(x)``, ``g_p(x) = A_p x - b_p``);
- sandwich covariance ``V = A^-1 (sum_p g_p g_p^T) A^-1`` at ``x^``. Expanded,
  ``sum_p g_p g_p^T = L S_AA L^T - L S_Ab - S_Ab^T L^T + S_bb`` with ``A_p x = L(x) alpha_p``,
  ``S_AA = sum_p alpha_p alpha_p^T`` (21 numbers), ``S_Ab = sum_p alpha_p b_p^T`` (18) and
  ``S_bb = sum_p b_p b_p^T`` (6): fixed-size, incremental;
- small-sample correction: the residuals ``g_p(x^)`` sum to zero, so the plug-in meat
  under-counts by ``(G-1)/G`` (CR1 factor ``G/(G-1)``); and with the meat estimated from
  ``G`` passes, ``(x^ - x)^T V^-1 (x^ - x)`` on the horizontal plane follows Hotelling's
  ``T^2(2, G-1) = 2 (G-1)/(G-2) F(2, G-2)`` rather than chi-square(2), so the reported
  covariance is ``kappa(G) V`` with ``kappa = T^2_0.95 / chi2_2,0.95`` (1.16 at ``G = 30``,
  1.67 at ``G = 10``, 4.25 at ``G = 5``). Per axis that is slightly conservative;
- model floor: the reported covariance is at least the model-based ``A^-1`` (what the
  reported sigmas alone imply, valid with inverse-variance weights), as a Loewner maximum;
- second-order bias correction: ``A`` is itself noisy (very much so once compensated) and
  ``E[A^-1 b] - x = A^-1 E[dA A^-1 G(x)] + O(G^-2)``; the same pass sums estimate it as
  ``beta = A^-1 sum_p A_p A^-1 g_p(x^)``, and ``x = x^ - beta`` is reported;
- second-order variance: the noise of ``A`` adds ``A^-1 (sum_p A_p V A_p - A V A/G) A^-1``
  (delta method; ``sum_p A_p V A_p`` contracts ``S_AA`` with ``V``);
- integrated meat: the meat averaged over ``x ~ N(x^, V)`` rather than taken at ``x^``,
  ``sum_p g_p g_p^T + sum_p A_p V A_p``, then the sandwich and the second-order term again
  (``EstimatorConfig.integrated_meat``);
- conditioning: ``A`` positive definite with condition number ``<= max_cond``; every
  eigenvalue ``lambda_k`` (eigenvector ``u_k``) of the *predicted* information ``J`` at
  least ``min_significance`` times the between-pass standard error of ``A`` in that
  direction, ``sqrt(G/(G-1) (nu_k^T S_AA nu_k - (u_k^T A u_k)^2 / G))`` with
  ``nu_k . alpha = u_k^T A u_k``; the same ratio for ``A``'s own eigenvalues at least
  ``min_realized_significance``; enough rays and passes.

>>> import numpy as np
>>> A = np.array([[2.0, 0, 0, 0, 0, 0]]) + np.array([[0, 2.0, 2.0, 0, 0, 0]])
>>> sol = solve_sums(A, np.array([[2.0, 4.0, 6.0]]), np.zeros((1, 21)), np.zeros((1, 6, 3)),
...                  np.zeros((1, 6)), np.array([10]), np.array([10]), EstimatorConfig())
>>> sol.x.round(6).tolist()
[[1.0, 2.0, 3.0]]
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from hdmap.mapping.estimator.model import (
    SYM_BASIS,
    EstimatorConfig,
    apply_matrix,
    sym_to_mat,
    tri_to_mat6,
)

Array = NDArray[np.float64]
_SYM_INDEX9 = np.array([0, 3, 4, 3, 1, 5, 4, 5, 2])  # 3x3 entry (row-major) -> 6-vector slot
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Solution:
    """Per queried landmark (struct of arrays). ``x`` and ``cov`` are NaN where ``A`` is not
    positive definite; publish only where ``ok``."""

    x: Array
    """(m, 3) estimate (bias-corrected when configured), tile ENU metres."""
    cov: Array
    """(m, 3, 3) reported covariance (sandwich, small-sample inflation, model floor)."""
    ok: BoolArray
    """Well-conditioned and enough data to publish."""
    n_obs: IntArray
    n_clusters: IntArray
    """Passes (clusters) so far, open ones included; rays when ``cluster_robust`` is off."""
    x_raw: Array
    """``A^-1 b`` before the bias correction."""
    bias: Array
    """Estimated bias subtracted from ``x_raw`` (zero when the correction is off)."""
    cov_sandwich: Array
    """``A^-1 meat A^-1`` with the CR1 factor, before inflation and floor."""
    inflation: Array
    """Small-sample factor ``kappa(G)`` applied to ``cov_sandwich``."""
    cond: Array
    """Condition number of ``A`` (inf where not positive definite)."""
    significance: Array
    """Smallest eigenvalue of ``A`` over its between-pass standard error."""
    dispersion: Array
    """``trace(A^-1 meat) / 3``: about 1 when the reported sigmas explain the scatter and
    rays are independent (textbook terms); much larger flags unreported or shared noise."""

    def __len__(self) -> int:
        return int(self.ok.shape[0])


def hotelling_inflation(g: NDArray, level: float = 0.95, dims: int = 2) -> Array:
    """``T^2_level(dims, G-1) / chi2_level(dims)``; ``G <= dims`` gets the ``G = dims + 1``
    value (the region is then set by the model floor, not by the between-pass spread).

    >>> hotelling_inflation(np.array([5, 10, 30, 1000])).round(3).tolist()
    [4.251, 1.674, 1.155, 1.004]
    """
    g = np.maximum(np.asarray(g, float), dims + 1.0)
    u, inv = np.unique(g, return_inverse=True)  # few distinct pass counts: ppf once each
    return np.array([_hotelling(float(v), level, dims) for v in u])[inv].reshape(g.shape)


def preload() -> None:
    """Import what :func:`hotelling_inflation` needs (scipy.stats: 0.5-1.2 s of CPU) now: a
    service calls it at start so that its first batch does not wait for the import."""
    hotelling_inflation(np.array([5.0]))


@lru_cache(maxsize=4096)
def _hotelling(g: float, level: float, dims: int) -> float:
    # scipy is imported here, not at the top: the onboard side imports this package (for
    # the gating statistic) on vehicles that do not install scipy, and never solves.
    from scipy import stats

    q = stats.chi2.ppf(level, dims)
    return float(dims * (g - 1.0) / (g - dims) * stats.f.ppf(level, dims, g - dims) / q)


def meat_matrix(x: Array, saa: Array, sab: Array, sbb: Array) -> Array:
    """``sum_p (A_p x - b_p)(A_p x - b_p)^T`` from the pass sums (m, 3, 3)."""
    lm = apply_matrix(x)
    s6 = tri_to_mat6(saa)
    lab = lm @ sab
    return lm @ s6 @ np.swapaxes(lm, -1, -2) - lab - np.swapaxes(lab, -1, -2) + sym_to_mat(sbb)


def bias_estimate(x: Array, k: Array, saa: Array, sab: Array) -> Array:
    """``A^-1 sum_p A_p A^-1 (A_p x - b_p)`` from the pass sums (``k = A^-1``)."""
    t1 = np.einsum("tijkl,tjk,tl->ti", pass_tensor(saa), k, x)
    ek = np.einsum("mij,tjk->tmik", SYM_BASIS, k)
    t2 = np.einsum("tmik,tmk->ti", ek, sab)
    return np.einsum("tij,tj->ti", k, t1 - t2)


def pass_tensor(saa: Array) -> Array:
    """``S[i, j, k, l] = sum_p (A_p)_ij (A_p)_kl`` (m, 3, 3, 3, 3) from the packed ``S_AA``."""
    idx = _SYM_INDEX9
    s6 = tri_to_mat6(saa)
    return s6[:, idx][:, :, idx].reshape(-1, 3, 3, 3, 3)


def pass_contraction(s4: Array, v: Array) -> Array:
    """``sum_p A_p V A_p`` (m, 3, 3) from :func:`pass_tensor` ``s4``: also the expected
    change of the meat ``sum_p g_p g_p^T`` when ``x`` moves by a zero-mean step of
    covariance ``V``.

    >>> saa = np.zeros((1, 21)); saa[0, 0] = 4.0  # one pass with A_p = diag(2, 0, 0)
    >>> pass_contraction(pass_tensor(saa), np.eye(3)[None])[0].diagonal().tolist()
    [4.0, 0.0, 0.0]
    """
    # summed term by term in a fixed order: an einsum's summation order follows how its
    # iterator lays the loops out, which depends on the stack's length (a landmark solved
    # alone and in a batch then differs in the last bits, and the solver's publish would
    # follow how its input was batched)
    out = np.zeros((s4.shape[0], 3, 3))
    for j in range(3):
        for kk in range(3):
            out += s4[:, :, j, kk, :] * v[:, j, kk, None, None]
    return out


def second_order_term(v: Array, amat: Array, k: Array, s4: Array, g: Array) -> Array:
    """``A^-1 (sum_p A_p V A_p - A V A / G) A^-1``: the variance the noise of ``A`` adds to
    ``A^-1 b`` at second order (``sum_p A_p V A_p`` from :func:`pass_tensor` ``s4``),
    symmetrised, >= 0."""
    t = pass_contraction(s4, v)
    gg = np.maximum(np.asarray(g, float), 1.0)[:, None, None]
    w = k @ (t - amat @ v @ amat / gg) @ k
    w = 0.5 * (w + np.swapaxes(w, -1, -2))
    lam, u = np.linalg.eigh(w)
    return (u * np.maximum(lam, 0.0)[..., None, :]) @ np.swapaxes(u, -1, -2)


MAX_PULL = 0.5
"""Largest pull ``kappa`` used (a larger one means the weights, not the data, set ``A``)."""


def pull_inflation(pull: Array, amat: Array) -> Array:
    """``1 / (1 - kappa)^2``, ``kappa = pull / (A_EE + A_NN)`` clipped to ``[0, MAX_PULL]``
    (``EstimatorConfig.extra_sigma_pos_m``): each pass is pulled toward the previous
    estimate by ``kappa``, so the error carries ``1 / (1 - kappa)`` of each pass's own.

    >>> pull_inflation(np.array([0.0, 2.0]), np.stack([np.eye(3) * 5.0] * 2)).round(6).tolist()
    [1.0, 1.5625]
    """
    tr = amat[:, 0, 0] + amat[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(tr > 0, np.asarray(pull, float) / tr, 0.0)
    k = np.clip(np.nan_to_num(k), 0.0, MAX_PULL)
    return 1.0 / (1.0 - k) ** 2


def loewner_max(v: Array, floor: Array) -> Array:
    """Smallest-change matrix ``>=`` both ``v`` and the positive definite ``floor``: whiten by
    ``floor``, clip the eigenvalues of ``v`` at 1, colour back.

    >>> loewner_max(np.diag([4.0, 0.5])[None], np.eye(2)[None])[0].tolist()
    [[4.0, 0.0], [0.0, 1.0]]
    """
    c = np.linalg.cholesky(floor)
    ci = np.linalg.inv(c)
    w = ci @ v @ np.swapaxes(ci, -1, -2)
    lam, u = np.linalg.eigh(0.5 * (w + np.swapaxes(w, -1, -2)))
    lam = np.maximum(lam, 1.0)
    cu = c @ u
    return (cu * lam[..., None, :]) @ np.swapaxes(cu, -1, -2)


def _significance(
    lam: Array, vec: Array, s6: Array, g: Array, realized: Array | None = None
) -> Array:
    """min_k lambda_k / se_k, ``se_k`` from the between-pass spread of ``u_k^T A_p u_k``
    (``realized`` = ``u_k^T A u_k``, default ``lambda_k``: the directions are A's own)."""
    realized = lam if realized is None else realized
    v0, v1, v2 = vec[:, 0, :], vec[:, 1, :], vec[:, 2, :]
    nu = np.stack([v0 * v0, v1 * v1, v2 * v2, 2 * v0 * v1, 2 * v0 * v2, 2 * v1 * v2], axis=1)
    second = np.einsum("tmk,tmn,tnk->tk", nu, s6, nu)
    gg = np.maximum(g, 2.0)[:, None]
    var = gg / (gg - 1.0) * (second - realized**2 / gg)
    se = np.sqrt(np.maximum(var, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        sig = np.where(se > 0, lam / se, np.where(lam > 0, np.inf, 0.0))
    sig = sig.min(axis=1)
    return np.where(g >= 2, sig, 0.0)


def solve_sums(
    a6: Array,
    b: Array,
    saa: Array,
    sab: Array,
    sbb: Array,
    n_obs: IntArray,
    n_clusters: IntArray,
    cfg: EstimatorConfig,
    j6: Array | None = None,
    floor_scale: Array | None = None,
    pull: Array | None = None,
) -> Solution:
    """Solve every landmark from its sums (all coordinates relative to its anchor).

    ``floor_scale`` (per landmark, default 1) multiplies the model floor ``A^-1``: with ray
    weights ``c`` (a vehicle's trust) it is ``sum c^2 / sum c``, the weighted least
    squares variance for equal true variances (weights all 0.05 give the same floor as
    weights all 1). ``pull`` (per landmark, default 0) is ``sum_j tr C_j``
    (:func:`hdmap.mapping.estimator.model.pull_terms`): the covariance is divided by
    ``(1 - kappa)^2``, ``kappa = pull / (A_EE + A_NN)`` (at most ``MAX_PULL``)."""
    m = a6.shape[0]
    amat = sym_to_mat(a6)
    lam, vec = np.linalg.eigh(amat)
    pd = np.isfinite(lam).all(axis=1) & (lam[:, 0] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(pd, lam[:, -1] / np.where(pd, lam[:, 0], 1.0), np.inf)
    safe = np.where(pd[:, None, None], amat, np.eye(3))
    k = np.linalg.inv(safe)
    x_raw = np.einsum("tij,tj->ti", k, b)
    g = np.asarray(n_clusters, float)
    meat = meat_matrix(x_raw, saa, sab, sbb)
    cr1 = np.where(g >= 2, g / np.maximum(g - 1.0, 1.0), 1.0)
    s4 = pass_tensor(saa) if cfg.second_order_variance or cfg.integrated_meat else None

    def sandwich(mt: Array) -> tuple[Array, Array]:
        """CR1 sandwich of meat ``mt``, and it with the second-order term (if configured)."""
        v = cr1[:, None, None] * (k @ mt @ k)
        v = 0.5 * (v + np.swapaxes(v, -1, -2))
        return v, (v + second_order_term(v, amat, k, s4, g) if cfg.second_order_variance else v)

    v_s, cov = sandwich(meat)
    if cfg.integrated_meat:
        # the meat at x ~ N(x^, cov) on average, not at x^ (EstimatorConfig.integrated_meat)
        v_s, cov = sandwich(meat + pass_contraction(s4, cov))
    kappa = hotelling_inflation(g, cfg.coverage_level) if cfg.small_sample else np.ones(m)
    cov = kappa[:, None, None] * cov
    if pull is not None:
        cov = cov * pull_inflation(pull, amat)[:, None, None]
    if cfg.model_floor and cfg.weighting == "inverse_variance":
        fs = np.ones(m) if floor_scale is None else np.asarray(floor_scale, float)
        cov = loewner_max(cov, k * fs[:, None, None])
    bias = np.zeros((m, 3))
    if cfg.bias_correction:
        bias = np.where((g >= 2)[:, None], bias_estimate(x_raw, k, saa, sab), 0.0)
        # the estimate of an O(1/G) bias is itself noisy where A is: never move the
        # estimate by more than one reported standard deviation (Mahalanobis)
        with np.errstate(all="ignore"):
            d2 = np.einsum("ti,tij,tj->t", bias, np.linalg.pinv(cov), bias)
            bias = bias * np.where(d2 > 1.0, 1.0 / np.sqrt(d2), 1.0)[:, None]
        bias = np.where(np.isfinite(bias), bias, 0.0)
    x = x_raw - bias
    s6 = tri_to_mat6(saa)
    signif_a = _significance(lam, vec, s6, g)
    signif = signif_a
    if cfg.significance_basis == "predicted" and j6 is not None:
        lam_j, vec_j = np.linalg.eigh(sym_to_mat(j6))
        on_a = np.einsum("tik,tij,tjk->tk", vec_j, amat, vec_j)
        signif = _significance(lam_j, vec_j, s6, g, on_a)
    dispersion = np.einsum("tii->t", k @ meat) / 3.0
    ok = (
        pd
        & (cond <= cfg.max_cond)
        & (np.asarray(n_obs) >= cfg.min_rays)
        & (g >= cfg.min_clusters)
        & (signif >= cfg.min_significance)
        & (signif_a >= cfg.min_realized_significance)
        & np.isfinite(x).all(axis=1)
        & np.isfinite(cov).all(axis=(1, 2))
    )
    nan3 = np.where(pd[:, None], 0.0, np.nan)
    return Solution(
        x=x + nan3,
        cov=cov + nan3[:, :, None],
        ok=ok,
        n_obs=np.asarray(n_obs, np.int64),
        n_clusters=np.asarray(n_clusters, np.int64),
        x_raw=x_raw + nan3,
        bias=bias,
        cov_sandwich=v_s + nan3[:, :, None],
        inflation=kappa,
        cond=cond,
        significance=signif,
        dispersion=dispersion,
    )
