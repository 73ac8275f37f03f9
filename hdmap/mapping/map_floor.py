"""The map's covariance floor: the error that more passes do not average away, measured
against surveyed signs (control points).

The solver's covariance is the between-pass sandwich (:mod:`hdmap.mapping.estimator.solve`):
it measures what varies from pass to pass and shrinks as ``1/G``. What every pass of a
landmark shares stays: a neighbour's rays the matcher gave it, the bias of the pass
weights (a nonlinear function of each pass's own noisy sums), geometry every car repeats
(the same lanes, the same curves). Past a few hundred passes that is most of the error, and
a covariance without it claims a 95 % region that holds 84-89 % of the signs (issue #18).
It reaches the published covariance as ``s^2 I`` per axis
(``SolverConfig.systematic_sigma_m``) or as a pass correlation
(``SolverConfig.pass_correlation``, :func:`pass_correlation`), and is measured here (both
forms from the same controls: :func:`measure_forms`), not typed in.

Given ``n`` control landmarks (a landmark paired with a surveyed sign), their errors
``e_i`` (``k`` axes: East and North, or Up) and the covariances ``C_i`` they were
published with, which already hold a floor ``s0^2 I``, the floor is the smallest ``s >= 0``
for which a share ``level`` of the controls lie inside their region:

    e_i^T (C_i - s0^2 I + s^2 I)^-1 e_i <= chi2_k(level).

Per control the statistic falls as ``s`` grows, so each has the least floor ``s_i`` that
takes it inside (0 if it already is), and the map's floor is the order statistic of rank
``ceil(level (n + 1))`` of the ``s_i``: the split-conformal quantile, so that a new
landmark from the same population as the controls is inside its region with probability at
least ``level`` (the plain rank ``ceil(level n)`` gives ``level n / (n + 1)``: 0.945 with
200 controls). Its distribution-free interval comes from the binomial count of controls
below a quantile (:func:`quantile_interval`).

Why a quantile and not a second moment (``mean(e e^T - C)``): a landmark holding a
neighbour's rays is metres off, and one of them in 200 controls moves a second moment by
more than the floor itself; the quantile asks only what the map claims, that 95 % of the
signs lie inside their 95 % regions.

Pitfall: the floor is measured where the rest has averaged out (controls with many passes;
the fleet evaluation takes 150+): measured at 30 passes it is hidden under the sandwich
and comes out near 0; it then over-covers slightly where passes are few (the target range
0.90-0.98 allows it).

>>> e = np.array([[0.3, 0.0], [0.0, 0.3], [0.1, 0.1], [0.0, 0.0]])
>>> c = np.repeat(np.eye(2)[None] * 0.01, 4, axis=0)
>>> f = coverage_floor(e, c, level=0.75)
>>> round(f.value, 3), f.inside_before, f.inside_after
(0.15, 0.5, 1.0)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import binom, chi2

Array = NDArray[np.float64]

MIN_CONTROLS = 20
"""Fewest paired controls a floor is measured from: with fewer, the conformal rank of a
0.95 quantile is the largest value (``ceil(0.95 (n + 1)) >= n`` for ``n <= 19``)."""


@dataclass(frozen=True)
class FloorFit:
    """A measured floor parameter and what it was measured from."""

    parameter: str
    """``sigma_m``: the per-axis sigma ``s`` of an added ``s^2 I`` (m); ``kappa``: the pass
    correlation of ``V (1 + kappa G)`` (:func:`pass_correlation`)."""
    value: float
    interval: tuple[float, float]
    """Distribution-free interval of ``value`` (:func:`quantile_interval`, ``confidence``)."""
    controls: int
    level: float
    confidence: float
    inside_before: float
    """Share of the controls inside their regions as published."""
    inside_after: float
    """The same with the measured floor in place of the published one."""
    least: tuple[float, ...] = ()
    """Per control, the least value that takes it inside (what several sets of controls
    pool: :func:`quantile_interval` of their union)."""

    def as_dict(self) -> dict:
        return {
            self.parameter: self.value,
            "interval": list(self.interval),
            "least": list(self.least),
            "controls": self.controls,
            "level": self.level,
            "confidence": self.confidence,
            "inside_before": self.inside_before,
            "inside_after": self.inside_after,
        }


def horizontal_block(cov6: Array) -> Array:
    """(n, 6) ENU covariances as on the wire (ee en eu nn nu uu) -> (n, 2, 2) East/North."""
    c = np.asarray(cov6, float).reshape(-1, 6)
    return np.stack([np.stack([c[:, 0], c[:, 1]], -1), np.stack([c[:, 1], c[:, 3]], -1)], -2)


def mahalanobis2(err: Array, cov: Array) -> Array:
    """``e_i^T C_i^-1 e_i`` for (n, k) errors and (n, k, k) covariances."""
    return np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])


def without_floor(cov: Array, base_sigma_m: float) -> Array:
    """``C - s0^2 I``, its eigenvalues kept above 1e-12 m^2 (a covariance published
    without the whole floor stays positive definite)."""
    c = np.asarray(cov, float)
    w, v = np.linalg.eigh(c - base_sigma_m**2 * np.eye(c.shape[-1]))
    return (v * np.maximum(w, 1e-12)[..., None, :]) @ np.swapaxes(v, -1, -2)


def least_scales(err: Array, own: Array, shape: Array, level: float, iterations: int = 60) -> Array:
    """Per control, the least ``t_i >= 0`` that puts it inside its ``level`` region
    ``own_i + t_i shape_i`` (0 if inside already). Bisection on each ``t_i``, all at once;
    the upper bracket ``e_i^T shape_i^-1 e_i / chi2_k(level)`` is inside whatever
    ``own_i`` is (positive definite ``shape_i``)."""
    err = np.asarray(err, float)
    q = chi2.ppf(level, err.shape[1])
    lo = np.zeros(err.shape[0])
    hi = mahalanobis2(err, shape) / q * (1.0 + 1e-9) + 1e-18
    inside0 = mahalanobis2(err, own) <= q
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        ok = mahalanobis2(err, own + mid[:, None, None] * shape) <= q
        hi = np.where(ok, mid, hi)
        lo = np.where(ok, lo, mid)
    return np.where(inside0, 0.0, hi)


def quantile_interval(
    values: Array, level: float, confidence: float = 0.95
) -> tuple[float, float, float]:
    """The conformal ``level`` quantile of ``values`` (the order statistic of rank
    ``ceil(level (n + 1))``, at most ``n``) and a distribution-free ``confidence`` interval
    for the population's ``level`` quantile: order statistics of ranks ``j``, ``k`` with
    ``P(j <= B < k) >= confidence``, ``B ~ Bin(n, level)`` the count of values below it
    (ranks clipped to the sample)."""
    x = np.sort(np.asarray(values, float))
    n = x.size
    if n == 0:
        raise ValueError("quantile_interval: no values")
    rank = min(max(int(np.ceil(level * (n + 1))), 1), n)
    a = (1.0 - confidence) / 2.0
    j = int(binom.ppf(a, n, level))  # B >= j with probability >= 1 - a
    k = int(binom.isf(a, n, level)) + 1
    return float(x[rank - 1]), float(x[max(j, 1) - 1]), float(x[min(k, n) - 1])


def _check(err: Array, cov: Array, level: float, confidence: float) -> None:
    if err.ndim != 2 or cov.shape != (*err.shape, err.shape[1]) or err.shape[0] == 0:
        raise ValueError("map floor: err (n, k) and cov (n, k, k), n >= 1")
    if not (0.0 < level < 1.0 and 0.0 < confidence < 1.0):
        raise ValueError("map floor: level and confidence in (0, 1)")


def _fit(
    parameter: str,
    err: Array,
    published: Array,
    own: Array,
    shape: Array,
    level: float,
    confidence: float,
    to_value=lambda t: t,
) -> FloorFit:
    least = least_scales(err, own, shape, level)
    t, lo, hi = quantile_interval(least, level, confidence)
    q = chi2.ppf(level, err.shape[1])
    return FloorFit(
        parameter=parameter,
        value=float(to_value(t)),
        interval=(float(to_value(lo)), float(to_value(hi))),
        controls=err.shape[0],
        level=level,
        confidence=confidence,
        inside_before=float(np.mean(mahalanobis2(err, published) <= q)),
        inside_after=float(np.mean(mahalanobis2(err, own + t * shape) <= q * (1 + 1e-9))),
        least=tuple(float(x) for x in to_value(least)),
    )


def coverage_floor(
    err: Array,
    cov: Array,
    level: float = 0.95,
    base_sigma_m: float = 0.0,
    confidence: float = 0.95,
    published: Array | None = None,
) -> FloorFit:
    """The per-axis floor ``s`` (``parameter`` ``sigma_m``) that puts a share ``level`` of
    the controls inside their ``level`` regions ``C_i - s0^2 I + s^2 I`` (see the module
    doc). ``err`` (n, k) landmark minus surveyed position, ``cov`` (n, k, k) holding
    ``base_sigma_m^2 I``; ``published`` what the map said, for ``inside_before`` (default
    ``cov``)."""
    err, cov = np.asarray(err, float), np.asarray(cov, float)
    _check(err, cov, level, confidence)
    if base_sigma_m < 0.0:
        raise ValueError("map floor: base_sigma_m >= 0")
    own = without_floor(cov, base_sigma_m)
    shape = np.broadcast_to(np.eye(err.shape[1]), cov.shape)
    pub = cov if published is None else np.asarray(published, float)
    return _fit("sigma_m", err, pub, own, shape, level, confidence, np.sqrt)


def pass_correlation(
    err: Array,
    between: Array,
    passes: NDArray[np.int64],
    published: Array,
    other: Array | None = None,
    level: float = 0.95,
    confidence: float = 0.95,
) -> FloorFit:
    """The pass correlation ``kappa`` (``parameter`` ``kappa``) that puts a share ``level``
    of the controls inside their regions ``V_i (1 + kappa G_i) + other_i``: ``V_i`` the
    between-pass covariance of control ``i`` (its ``G_i`` passes), ``other_i`` the floors
    kept as they are (a shared GNSS floor), ``published`` what the map said (for
    ``inside_before``).

    The model is Kish's design effect: if the errors of a landmark's passes share a part
    ``u`` with ``Var(u) = kappa Var(pass error)``, the between-pass scatter sees only the
    rest and the estimate's variance is ``V (1 + kappa G)``: a floor that grows with the
    passes where the sandwich shrinks, and along the direction each pass's error is
    largest (the line of sight of a sign seen head-on) rather than the same on every axis.
    """
    err, between = np.asarray(err, float), np.asarray(between, float)
    _check(err, between, level, confidence)
    own = between + (0.0 if other is None else np.asarray(other, float))
    shape = np.asarray(passes, float)[:, None, None] * between
    return _fit("kappa", err, np.asarray(published, float), own, shape, level, confidence)


def measure_forms(
    err: Array,
    cov6: Array,
    passes: NDArray[np.int64],
    kappa0: float,
    sigma0_m: Array,
    shared_m2: Array,
    level: float = 0.95,
    confidence: float = 0.95,
) -> dict[str, FloorFit]:
    """Both forms of the floor from controls whose covariances (``cov6``, (n, 6) ENU as on
    the wire) were published with a pass correlation ``kappa0``, a per-axis sigma
    ``sigma0_m`` (E, N, U; East and North equal) and a shared GNSS floor ``shared_m2``
    (3, 3): each published floor taken out first, each form measured alone (the solver is
    given one of them), the shared floor kept. ``horizontal`` and ``vertical``: the
    per-axis sigma (2D and 1D regions); ``pass_correlation``: kappa, horizontal."""
    err, g = np.asarray(err, float), np.asarray(passes, float)
    cov6 = np.asarray(cov6, float).reshape(-1, 6)
    s0, shared = np.asarray(sigma0_m, float), np.asarray(shared_m2, float)
    design = 1.0 + kappa0 * g
    pub_h = horizontal_block(cov6)
    between = without_floor(pub_h - shared[:2, :2], float(s0[0])) / design[:, None, None]
    v_between = np.maximum(cov6[:, 5] - shared[2, 2] - s0[2] ** 2, 1e-12) / design
    v_own = (v_between + shared[2, 2]).reshape(-1, 1, 1)
    return {
        "horizontal": coverage_floor(
            err[:, :2], between + shared[:2, :2], level, confidence=confidence, published=pub_h
        ),
        "vertical": coverage_floor(
            err[:, 2:3], v_own, level, confidence=confidence, published=cov6[:, 5].reshape(-1, 1, 1)
        ),
        "pass_correlation": pass_correlation(
            err[:, :2], between, g, pub_h, shared[:2, :2], level, confidence
        ),
    }


def pair_controls(
    lm_xyz: Array,
    lm_class: NDArray[np.int64],
    lm_passes: NDArray[np.int64],
    ctl_xyz: Array,
    ctl_class: NDArray[np.int64],
    match_m: float,
    min_passes: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Controls (surveyed signs) paired with landmarks (one local frame, m): each pair of
    one class, horizontally within ``match_m``, the landmark with ``min_passes`` passes
    or more; nearest pairs first, each control and landmark in at most one pair. Returns
    (control rows, landmark rows).

    >>> lm = np.array([[0.0, 0, 0], [3.0, 0, 0], [0.5, 0, 0]])
    >>> ctl = np.array([[0.2, 0, 0], [2.0, 0, 0]])
    >>> pair_controls(lm, np.array([1, 1, 2]), np.array([200] * 3), ctl, np.array([1, 1]), 5.0, 150)
    (array([0, 1]), array([0, 1]))
    """
    d = np.linalg.norm(ctl_xyz[:, None, :2] - lm_xyz[None, :, :2], axis=-1)
    ok = (ctl_class[:, None] == lm_class[None, :]) & (d <= match_m)
    ok &= (lm_passes >= min_passes)[None, :]
    ci, li = np.nonzero(ok)
    order = np.argsort(d[ci, li], kind="stable")
    used_c = np.zeros(len(ctl_xyz), bool)
    used_l = np.zeros(len(lm_xyz), bool)
    out_c, out_l = [], []
    for c, m in zip(ci[order].tolist(), li[order].tolist(), strict=True):
        if not (used_c[c] or used_l[m]):
            used_c[c] = used_l[m] = True
            out_c.append(c)
            out_l.append(m)
    return np.array(out_c, np.int64), np.array(out_l, np.int64)
