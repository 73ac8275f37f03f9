"""Ray model, configuration and the per-ray (bias-compensated) normal-equation terms.

A ray j has origin ``a_j`` and measured unit direction ``d_j = (cos e sin a, cos e cos a,
sin e)`` in a local ENU frame (azimuth ``a`` clockwise from North, elevation ``e``). Its
orthogonal-distance normal-equation term for a landmark at ``x`` is

    Q_j (x - a_j),    Q_j = w_v,j P_j + (w_h,j - w_v,j) H_j,

with ``P_j = I - d_j d_j^T`` (the textbook projector) and ``H_j = h_j h_j^T``,
``h_j = (cos a, -sin a, 0)`` the horizontal normal of the ray. ``P - H = v v^T`` is the
vertical normal ``v = (-sin e sin a, -sin e cos a, cos e)``, so ``Q`` weights the
horizontal (azimuth) and vertical (elevation) residuals separately:

    w_h = 1 / (s_az^2 rho^2 + s_h^2),
    w_v = 1 / (s_el^2 r^2 + s_h^2 sin^2 e + s_v^2 cos^2 e),

with ``rho``, ``r`` and ``e`` the horizontal range, range and elevation from ``a_j`` to the
landmark's *reference* position (its previous estimate), never from the ray's direction:
a weight that depends on the ray's own noise would bias the sums. They still depend on the
noisy *origin* through the range; for Gaussian origin noise Stein's lemma gives that bias
exactly, ``E[w(a) P_t delta] = P_t Sigma_a E[grad_a w]``, and
:func:`~hdmap.mapping.estimator.terms.ray_terms` subtracts
it (``EstimatorConfig.weight_correction``).

Bias compensation
-----------------
The measured angles are ``a ~ N(a_t, s_az^2)`` and ``e ~ N(e_t, s_el^2)``, independent.
``E[P_j] != P_t`` (the textbook sums are pulled toward the ray origins). Every entry of
``d d^T`` and ``h h^T`` is a sum of products of harmonics of ``a`` (``1, cos a, sin a,
cos 2a, sin 2a``) and of ``e``; since ``E[cos(k a)] = cos(k a_t) exp(-k^2 s^2 / 2)``
(same for ``sin``), multiplying each harmonic of order ``k`` by ``exp(k^2 s^2 / 2)`` gives
estimators ``D`` and ``H~`` with ``E[D] = d_t d_t^T`` and ``E[H~] = h_t h_t^T`` exactly:

    C_e  = (1 + f_e2 cos 2e) / 2                  (unbiased for cos^2 e)
    D_EE = C_e (1 - f_a2 cos 2a) / 2,   D_NN = C_e (1 + f_a2 cos 2a) / 2
    D_UU = (1 - f_e2 cos 2e) / 2,       D_EN = C_e f_a2 sin 2a / 2
    D_EU = f_e2 sin 2e / 2 * f_a1 sin a,  D_NU = f_e2 sin 2e / 2 * f_a1 cos a
    H~   = [[1 + f_a2 cos 2a, -f_a2 sin 2a], [-f_a2 sin 2a, 1 - f_a2 cos 2a]] / 2 (EN block)

with ``f_a1 = exp(s_az^2 / 2)``, ``f_a2 = exp(2 s_az^2)``, ``f_e2 = exp(2 s_el^2)``, so the
compensated ``Q~ = w_v (I - D) + (w_h - w_v) H~`` has ``E[Q~] = Q_t`` and the estimating
function ``sum_j Q~_j (x - a_j)`` is unbiased at the true ``x`` (origin noise enters
linearly and averages out). In 2D (``e = 0``, ``s_el = 0``) ``I - D = f_a2 (P - c I)`` with
``c = (1 - exp(-2 s^2)) / 2``: the compensated projector ``P_j - c_j I``
(docs/estimator.md s.3), rescaled.

Sums are kept relative to a per-landmark *anchor* (its first position) so that tile-frame
coordinates of hundreds of metres never enter the products.

The per-ray terms themselves (bearings and box ranges) are in
:mod:`hdmap.mapping.estimator.terms`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.signs import DEFAULT_SIZE_REL_SIGMA

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

# Symmetric 3x3 matrices are stored as 6-vectors (EE, NN, UU, EN, EU, NU).
SYM_I = np.array([0, 1, 2, 0, 0, 1])
SYM_J = np.array([0, 1, 2, 1, 2, 2])
_SYM_INDEX = np.array([[0, 3, 4], [3, 1, 5], [4, 5, 2]])
SYM_BASIS = np.zeros((6, 3, 3))
"""``A = sum_m alpha_m SYM_BASIS[m]`` for the 6-vector ``alpha`` of a symmetric ``A``."""
for _m, (_i, _j) in enumerate(zip(SYM_I, SYM_J, strict=True)):
    SYM_BASIS[_m, _i, _j] = SYM_BASIS[_m, _j, _i] = 1.0

# Symmetric 6x6 matrices (outer products of 6-vectors) as 21-vectors (upper triangle).
TRI6_I, TRI6_J = np.triu_indices(6)
_TRI6_INDEX = np.zeros((6, 6), np.int64)
_TRI6_INDEX[TRI6_I, TRI6_J] = _TRI6_INDEX[TRI6_J, TRI6_I] = np.arange(21)


def mat_to_sym(m: ArrayLike) -> Array:
    """(..., 3, 3) symmetric -> (..., 6).

    >>> mat_to_sym(np.arange(9.0).reshape(3, 3) + np.arange(9.0).reshape(3, 3).T).tolist()
    [0.0, 8.0, 16.0, 4.0, 8.0, 12.0]
    """
    a = np.asarray(m, float)
    return a[..., SYM_I, SYM_J]


def row_dot(a: Array, b: Array) -> Array:
    """Per row ``a_k . b_k`` of (n, 3) arrays, summed in a fixed order (x, y, z): unlike an
    einsum, whose summation order follows how its iterator lays out the loops for the
    array's length, the same row gives the same bits in a batch of any size (the sums of
    :class:`~hdmap.mapping.estimator.sums.LandmarkSums` must not depend on how rays were
    cut into calls).

    >>> row_dot(np.array([[1.0, 2.0, 3.0]]), np.array([[4.0, 5.0, 6.0]])).tolist()
    [32.0]
    """
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def row_matvec(m: Array, v: Array) -> Array:
    """Per row ``M_k v_k`` of (n, 3, 3) and (n, 3) arrays, in a fixed order (see
    :func:`row_dot`).

    >>> row_matvec(np.eye(3)[None] * 2.0, np.array([[1.0, 2.0, 3.0]])).tolist()
    [[2.0, 4.0, 6.0]]
    """
    return m[:, :, 0] * v[:, 0, None] + m[:, :, 1] * v[:, 1, None] + m[:, :, 2] * v[:, 2, None]


def sym_to_mat(s: ArrayLike) -> Array:
    """(..., 6) -> (..., 3, 3) symmetric."""
    a = np.asarray(s, float)
    return a[..., _SYM_INDEX]


def outer6_to_tri(u: Array, v: Array | None = None) -> Array:
    """Symmetrised outer product of 6-vectors, packed as 21-vectors: (..., 21)."""
    v = u if v is None else v
    return 0.5 * (u[..., TRI6_I] * v[..., TRI6_J] + u[..., TRI6_J] * v[..., TRI6_I])


def tri_to_mat6(t: ArrayLike) -> Array:
    """(..., 21) -> (..., 6, 6) symmetric."""
    a = np.asarray(t, float)
    return a[..., _TRI6_INDEX]


def pass_weighted(a6: Array, b: Array, sigma: ArrayLike) -> tuple[Array, Array]:
    """Per pass, ``(W_p, b~_p) = ((I + A_p S)^-1 A_p, (I + A_p S)^-1 b_p)`` with ``S =
    diag(sigma^2)``, from the pass's raw sums as 6-vector ``a6`` (k, 6) and ``b`` (k, 3).

    ``sigma`` is (3,) or per pass (k, 3). ``W_p^-1 = A_p^-1 + S``: the pass's own
    estimate ``A_p^-1 b_p`` with the shared error
    added to its covariance, and ``W_p A_p^-1 b_p = b~_p`` (defined for singular ``A_p``
    too). Translating the origin by ``d`` moves ``b~_p`` by ``W_p d``, as it moves ``b_p``
    by ``A_p d``. A pass with huge information brings about ``S^-1``:

    >>> w, bt = pass_weighted(np.array([[1e6, 1e6, 1e6, 0, 0, 0]]), np.array([[1e6, 0, 0]]),
    ...                       (2.0, 2.0, 2.0))
    >>> w.round(4).tolist(), bt.round(4).tolist()
    ([[0.25, 0.25, 0.25, 0.0, 0.0, 0.0]], [[0.25, 0.0, 0.0]])
    """
    s2 = np.square(np.asarray(sigma, float))
    if not s2.any() or a6.shape[0] == 0:
        return a6, b
    a = sym_to_mat(a6)
    m = np.eye(3) + a * np.broadcast_to(s2, (a6.shape[0], 3))[:, None, :]  # I + A S
    # singular only for a compensated A_p with an eigenvalue near -1/s^2 (noise, or
    # hostile input): such a pass enters unweighted
    good = np.abs(np.linalg.det(m)) > 1e-9
    m[~good] = np.eye(3)
    w = np.linalg.solve(m, a)
    bt = np.linalg.solve(m, b[..., None])[..., 0]
    return mat_to_sym(0.5 * (w + np.swapaxes(w, -1, -2))), bt


def apply_matrix(x: Array) -> Array:
    """``L(x)`` (..., 3, 6) with ``A x = L(x) alpha`` for the 6-vector ``alpha`` of ``A``.

    >>> A = np.array([[2.0, 1, 0], [1, 3, 4], [0, 4, 5]])
    >>> x = np.array([1.0, 2.0, 3.0])
    >>> bool(np.allclose(apply_matrix(x) @ mat_to_sym(A), A @ x))
    True
    """
    x = np.asarray(x, float)
    out = np.zeros((*x.shape[:-1], 3, 6))
    e, n, u = x[..., 0], x[..., 1], x[..., 2]
    out[..., 0, 0], out[..., 0, 3], out[..., 0, 4] = e, n, u
    out[..., 1, 1], out[..., 1, 3], out[..., 1, 5] = n, e, u
    out[..., 2, 2], out[..., 2, 4], out[..., 2, 5] = u, e, n
    return out


@dataclass(frozen=True)
class EstimatorConfig:
    """Every knob of the landmark estimator; the defaults are our estimator.

    :meth:`paper` gives the paper's textbook estimator (the baseline).
    """

    box_range: bool = False
    """Rays' box ranges enter the normal equations as constraints along the rays
    (:func:`~hdmap.mapping.estimator.terms.range_terms`); False: bearings only (the paper's)."""
    range_scale: Literal["nominal", "per_pass", "inverse"] = "per_pass"
    """With ``box_range``: ``nominal`` takes the ranges as they are (the panel at its class's
    nominal size); ``per_pass`` gives each pass its own unknown range scale ``s`` (``d . (x -
    a) = s r``), eliminated when the pass enters the sums
    (:func:`~hdmap.mapping.estimator.terms.scale_terms`), so only the
    ratios of one pass's ranges count (how the box grows as the car drives at the sign),
    whatever the panel's real size; ``inverse`` is the same in inverse range (``rho d . (x -
    a) = s``), its box-noise bias compensated by the noise measured from the passes
    (:mod:`~hdmap.mapping.estimator.box_noise`)."""
    panel_rel_sigma: float = DEFAULT_SIZE_REL_SIGMA
    """The sign catalogue's relative panel-size spread that every ray's ``sigma_range_m``
    includes (the catalogue's default); the inverse form takes it out to get the box's
    white part (the panel's scale is the pass's unknown)."""
    range_noise_prior_dof: float = 4.0
    """Pseudo degrees of freedom of the vehicle's claimed box noise in the measured ratio
    (:func:`~hdmap.mapping.estimator.box_noise.noise_ratio`)."""
    compensate: bool = True
    """Bias-compensated sums (``E[Q~_j] = Q_t``); False = the textbook orthogonal-distance
    sums of the paper's eq. (4), biased toward the ray origins when direction noise is large."""
    cluster_robust: bool = True
    """Covariance from the spread *between passes* (cluster sandwich; rays of one pass share
    a GNSS bias). False = every ray is its own cluster (ray-level sandwich), which is
    over-confident when errors are correlated within a pass."""
    weighting: Literal["inverse_variance", "uniform"] = "inverse_variance"
    """``inverse_variance``: ``w_h``, ``w_v`` from the reported sigmas and the range to the
    landmark's reference position. ``uniform``: every ray weighs 1 (paper's eq. (4))."""
    extra_sigma_az: float = 0.0
    """Unreported azimuth noise, rad, added in quadrature to every ray's ``sigma_az`` (for the
    compensation, the weights and the gate). A per-pass heading bias the receiver does not
    report is such noise: without it the compensation is too weak and the estimate keeps a
    bias toward the ray origins. Calibrate it with :func:`excess_angular_variance`."""
    extra_sigma_el: float = 0.0
    """Unreported elevation noise (pitch, mounting), rad, added like ``extra_sigma_az``."""
    extra_sigma_pos_m: float = 0.0
    """Unreported origin error shared by a pass (GNSS position bias), m per horizontal axis:
    the position counterpart of ``extra_sigma_az``. The weights depend on the origin through
    the range, and the Stein correction (``weight_correction``) removes only the part of
    that dependence the reported (white) origin noise explains; a shared bias leaves every
    pass pulled toward the reference position (the previous estimate) by
    ``kappa = tr C / tr_h A``, ``C = sum_j 2 s_az^2 w_h,j^2 sigma^2 H~_j``
    (:func:`pull_terms`), which links the passes and which the between-pass sandwich does
    not see. The reported covariance is divided by ``(1 - kappa)^2``; the estimate is left
    alone (taking the pull out of it costs accuracy along the road, where it acts as a
    regulariser). Meant for passes entered unweighted (the paper simulation's noise):
    with the pass weighting on, ``A`` is pass-weighted and the ratio overstates the pull,
    so the fleet's solver leaves it at 0. docs/estimator.md section 6."""
    min_range_m: float = 1.0
    """Floor on the ranges used in the weights (bounds the weight of one ray)."""
    weight_correction: bool = True
    """Stein correction for weights that depend on the (noisy) ray origin through the range:
    ``E[w(a) P_t delta] = P_t Sigma_a E[grad_a w]`` for Gaussian origin noise ``delta``, so
    ``-(M~ - H~) Sigma_a grad w_v - H~ Sigma_a grad w_h`` is added to each ray's estimating
    function. Without it the sums are pulled toward the reference position (a few percent
    per pass, compounding across passes: the between-pass covariance is then too small)."""
    min_sigma_pos_m: float = 0.05
    """Floor on the origin position sigmas used in the weights (bounds the weight of one ray)."""
    min_rays: int = 6
    """Rays a landmark needs before its estimate is published."""
    min_clusters: int = 5
    """Passes a landmark needs before its estimate is published (the between-pass
    covariance has ``G - 1`` degrees of freedom; fewer than 5 makes it meaningless)."""
    significance_basis: Literal["predicted", "realized"] = "predicted"
    """Directions and eigenvalues of the conditioning test: ``predicted`` uses the predicted
    information ``J = sum Q_ref`` (projectors toward the reference position, free of the
    direction noise), ``realized`` the compensated ``A`` itself (whose eigenvalues are
    correlated with the estimate's error: gating on them biases what gets published)."""
    min_realized_significance: float = 1.0
    """And the smallest eigenvalue of the compensated ``A`` itself must exceed this many of
    its standard errors (keeps near-singular realisations, whose ``A^-1 b`` is wild, out;
    kept low because gating on ``A``'s own eigenvalues selects by the error)."""
    max_cond: float = 1e7
    """Largest condition number of the compensated information matrix ``A``."""
    max_offset_m: float = 10_000.0
    """Largest distance of a usable estimate from its frame's origin (the home tile's
    centre, a few hundred metres from any sign filed there): a landmark whose rays do not
    meet (4,600 rays of 227 passes under one id with real phone errors, its sigma 415 m
    along the street) passed the conditioning test with an estimate 400 km away and 28 km
    up, which the solver published and no reader could decode
    (:func:`hdmap.mapping.estimator.provisional.usable`)."""
    min_significance: float = 3.0
    """Every eigenvalue of the information (``J`` or ``A``, see ``significance_basis``) must
    exceed this many standard errors of the compensated ``A`` in that direction (estimated
    from the between-pass spread of the per-pass matrices): ``A`` is a noisy estimate of the
    true information, and where the noise is comparable to the signal ``A^-1 b`` explodes."""
    bias_correction: bool = False
    """Subtract the O(1/G) bias of the ratio ``A^-1 b`` (estimated from the pass sums, capped
    at one reported standard deviation). Off by default: in the paper simulation it removed
    the bias at large G but over-corrected at small G (coverage 0.88 at 30-50 passes)."""
    second_order_variance: bool = True
    """Add the delta-method term of the noise of ``A`` itself:
    ``A^-1 (sum_p A_p V A_p - A V A / G) A^-1`` (``V`` the sandwich), about ``V / s^2`` in a
    direction whose eigenvalue is ``s`` standard errors from zero."""
    integrated_meat: bool = True
    """Evaluate the meat over the estimate's uncertainty instead of at the estimate:
    ``E[sum_p g_p(x) g_p(x)^T]`` for ``x ~ N(x^, V)`` is the plug-in meat plus
    ``sum_p A_p V A_p`` (``V`` the second-order sandwich; one step). The plug-in meat grows
    with the range from the origins to ``x^``, so an estimate pulled toward the road reports
    too small a region and one pushed away too large: in the paper simulation (white, 1,000
    trials, 30 passings) the fifth of trials with the smallest reported sigma (mostly those
    pulled toward the road) had 95 % coverage 0.75. Averaging
    over ``V`` raised the coverage at 30-50 passings from 0.926-0.943 to 0.943-0.959 (two
    seeds; sigma x1.1-1.2 there, x1.07 at 100). An O(1/G) term: about ``V / G`` where ``A``
    is well determined (the fleet)."""
    small_sample: bool = True
    """Inflate the sandwich for few passes: CR1 factor ``G / (G - 1)`` and the ratio of the
    95% Hotelling T^2 (2 dims, ``G - 1`` dof) to the chi-square(2) quantile."""
    model_floor: bool = True
    """Covariance at least the model-based ``A^-1`` (inverse-variance weights only)."""
    coverage_level: float = 0.95
    """Level of the region the small-sample inflation targets."""
    max_open_passes: int = 8
    """Per landmark, passes kept open (partial sums kept so later rays of the same pass join
    the same cluster). Opening one more closes the least recently active one."""
    pass_sigma_m: tuple[float, float, float] = (2.5, 2.5, 3.0)
    """Standard deviation (E, N, U) of the position error all rays of one pass share (GNSS
    bias, heading bias at range). Each pass enters the sums with the random-effects weight
    ``W_p = (I + A_p S)^-1 A_p`` and ``b~_p = (I + A_p S)^-1 b_p`` (``S = diag(sigma^2)``)
    instead of ``A_p``, ``b_p``: a pass brings at most ``S^-1`` of information however many
    rays it has (generalised least squares under a per-pass bias). Zeros: rays count alone
    (the paper's model). Only with ``cluster_robust`` (a pass is known)."""
    pass_weighting_max_sigma_rad: float = 0.05
    """A pass whose rays' RMS angular sigma (azimuth and elevation, as reported plus the
    extra terms) exceeds this enters unweighted: its sums are then mostly noise, and a
    weight computed from them (nonlinear in them) would bias the estimate."""

    @staticmethod
    def paper() -> EstimatorConfig:
        """The paper's estimator: textbook unweighted sums, every ray independent."""
        return EstimatorConfig(
            box_range=False,
            compensate=False,
            cluster_robust=False,
            weighting="uniform",
            bias_correction=False,
            second_order_variance=False,
            integrated_meat=False,
            small_sample=False,
            model_floor=False,
            min_significance=0.0,
            min_realized_significance=0.0,
            pass_sigma_m=(0.0, 0.0, 0.0),
        )


@dataclass(frozen=True)
class Rays:
    """Rays in ONE local metric frame (ENU metres of the landmark's home tile).

    ``direction`` is unit; ``sigma_az`` (azimuth, about Up) and ``sigma_el`` (elevation) are
    the reported angular standard deviations, rad; ``sigma_pos_h`` (per horizontal axis) and
    ``sigma_pos_v`` those of the origin, m.
    """

    origin: Array
    direction: Array
    sigma_az: Array
    sigma_el: Array
    sigma_pos_h: Array
    sigma_pos_v: Array
    weight: Array | None = None
    """Relative weight of each ray in (0, 1] (the matcher's trust in its vehicle); it
    multiplies ``w_h`` and ``w_v`` and leaves the noise model (and so the bias
    compensation) alone. None = 1 for all."""
    range_m: Array | None = None
    """Distance along the ray from the box size (0: none; :func:`vehicle.geoloc.box_range`),
    with ``sigma_range_m``; None: no ray has one
    (:func:`~hdmap.mapping.estimator.terms.range_terms`)."""
    sigma_range_m: Array | None = None

    def __len__(self) -> int:
        return int(np.asarray(self.origin).shape[0])

    def weights_or_ones(self) -> Array:
        n = len(self)
        return np.ones(n) if self.weight is None else np.asarray(self.weight, float)

    def take(self, idx: ArrayLike) -> Rays:
        """Rows ``idx`` (index array or boolean mask)."""
        i = np.asarray(idx)
        return Rays(
            **{
                f.name: None
                if getattr(self, f.name) is None
                else np.asarray(getattr(self, f.name))[i]
                for f in fields(self)
            }
        )

    @staticmethod
    def concat(parts: list[Rays]) -> Rays:
        optional = ("weight", "range_m", "sigma_range_m")
        cols = {
            f.name: np.concatenate([getattr(p, f.name) for p in parts])
            for f in fields(Rays)
            if f.name not in optional
        }
        if any(p.weight is not None for p in parts):
            cols["weight"] = np.concatenate([p.weights_or_ones() for p in parts])
        if any(p.range_m is not None for p in parts):
            for k in ("range_m", "sigma_range_m"):
                cols[k] = np.concatenate(
                    [np.zeros(len(p)) if p.range_m is None else getattr(p, k) for p in parts]
                )
        return Rays(**cols)

    @staticmethod
    def from_angles(
        origin: ArrayLike,
        az: ArrayLike,
        el: ArrayLike,
        sigma_az: ArrayLike,
        sigma_el: ArrayLike,
        sigma_pos_h: ArrayLike,
        sigma_pos_v: ArrayLike,
    ) -> Rays:
        """Rays from origins and measured (azimuth, elevation), sigmas broadcast to ``n``.

        >>> r = Rays.from_angles([[0.0, 0, 0]], [np.pi / 2], [0.0], 0.01, 0.01, 1.0, 1.0)
        >>> r.direction.round(12).tolist(), len(r)
        ([[1.0, 0.0, 0.0]], 1)
        """
        o = np.atleast_2d(np.asarray(origin, float))
        a, e = np.asarray(az, float), np.asarray(el, float)
        d = np.stack([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)], axis=-1)
        n = o.shape[0]

        def full(v: ArrayLike) -> Array:
            return np.broadcast_to(np.asarray(v, float), (n,)).copy()

        return Rays(
            o, d.reshape(n, 3), full(sigma_az), full(sigma_el), full(sigma_pos_h), full(sigma_pos_v)
        )


def ray_angles(direction: ArrayLike) -> tuple[Array, Array]:
    """(azimuth clockwise from North, elevation) of ENU directions (..., 3)."""
    d = np.asarray(direction, float)
    az = np.arctan2(d[..., 0], d[..., 1])
    el = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    return az, el


def effective_sigmas(rays: Rays, cfg: EstimatorConfig) -> tuple[Array, Array]:
    """Angular sigmas with the configured unreported noise added in quadrature."""
    s_az = np.hypot(np.asarray(rays.sigma_az, float), cfg.extra_sigma_az)
    s_el = np.hypot(np.asarray(rays.sigma_el, float), cfg.extra_sigma_el)
    return s_az, s_el


def weights(
    rays: Rays, origin_rel: Array, x_ref_rel: Array, cfg: EstimatorConfig
) -> tuple[Array, Array, Array, Array]:
    """Horizontal and vertical weights ``(w_h, w_v)`` of each ray against its landmark's
    reference position (both relative to the same anchor), and their gradients (n, 3) with
    respect to the ray origin (zero where a range floor applies, and for uniform weights).

    >>> r = Rays.from_angles([[0.0, 0, 0]], [0.0], [0.0], 0.1, 0.01, 1.0, 2.0)
    >>> w_h, w_v, g_h, g_v = weights(r, r.origin, np.array([[0, 10.0, 0]]), EstimatorConfig())
    >>> round(float(w_h[0]), 6), round(float(w_v[0]), 6), g_h[0].round(6).tolist()
    (0.5, 0.249377, [0.0, 0.05, 0.0])
    """
    n = len(rays)
    if cfg.weighting == "uniform":
        return np.ones(n), np.ones(n), np.zeros((n, 3)), np.zeros((n, 3))
    s_az, s_el = effective_sigmas(rays, cfg)
    v = x_ref_rel - origin_rel
    rho2_raw = v[:, 0] ** 2 + v[:, 1] ** 2
    rho2 = np.maximum(rho2_raw, cfg.min_range_m**2)
    r2_raw = rho2_raw + v[:, 2] ** 2
    r2 = np.maximum(rho2 + v[:, 2] ** 2, cfg.min_range_m**2)
    sin2e = v[:, 2] ** 2 / r2
    s_h2 = np.maximum(np.asarray(rays.sigma_pos_h, float), cfg.min_sigma_pos_m) ** 2
    s_v2 = np.maximum(np.asarray(rays.sigma_pos_v, float), cfg.min_sigma_pos_m) ** 2
    w_h = 1.0 / (s_az**2 * rho2 + s_h2)
    w_v = 1.0 / (s_el**2 * r2 + s_h2 * sin2e + s_v2 * (1.0 - sin2e))
    # gradients: w = 1/D  =>  grad_a w = -grad_v w = w^2 grad_v D  (v = x_ref - a)
    vh = v * np.array([1.0, 1.0, 0.0])
    g_h = (2.0 * s_az**2 * w_h**2)[:, None] * vh
    g_h[rho2_raw < cfg.min_range_m**2] = 0.0
    e_u = np.array([0.0, 0.0, 1.0])
    dd = (s_h2 - s_v2)[:, None] * (
        2.0 * (v[:, 2] / r2)[:, None] * e_u - (2.0 * v[:, 2] ** 2 / r2**2)[:, None] * v
    )
    g_v = (w_v**2)[:, None] * (2.0 * s_el[:, None] ** 2 * v + dd)
    g_v[(rho2_raw < cfg.min_range_m**2) | (r2_raw < cfg.min_range_m**2)] = 0.0
    if rays.weight is not None:
        wt = np.asarray(rays.weight, float)
        w_h, w_v, g_h, g_v = w_h * wt, w_v * wt, g_h * wt[:, None], g_v * wt[:, None]
    return w_h, w_v, g_h, g_v


def projector_terms(
    az: Array, el: Array, s_az: Array, s_el: Array, compensate: bool
) -> tuple[Array, Array]:
    """``(I - D, H~)`` as 6-vectors (n, 6): the (compensated) projector onto the plane
    normal to the ray and the projector onto its horizontal normal.

    With ``compensate=False`` these are exactly ``P = I - d d^T`` and ``h h^T``.

    >>> from hdmap.geo.geodesy import direction_from_angles
    >>> m, h = projector_terms(np.array([0.4]), np.array([0.2]), np.zeros(1), np.zeros(1),
    ...                        False)
    >>> d = direction_from_angles(0.4, 0.2)
    >>> bool(np.allclose(sym_to_mat(m)[0], np.eye(3) - np.outer(d, d)))
    True
    """
    if compensate:
        fa1 = np.exp(0.5 * s_az**2)
        fa2 = np.exp(2.0 * s_az**2)
        fe2 = np.exp(2.0 * s_el**2)
    else:
        fa1 = fa2 = fe2 = np.ones_like(az)
    c2a, s2a = fa2 * np.cos(2 * az), fa2 * np.sin(2 * az)
    c2e, s2e = fe2 * np.cos(2 * el), fe2 * np.sin(2 * el)
    ce2 = 0.5 * (1.0 + c2e)
    m = np.empty((az.shape[0], 6))
    m[:, 0] = 1.0 - 0.5 * ce2 * (1.0 - c2a)
    m[:, 1] = 1.0 - 0.5 * ce2 * (1.0 + c2a)
    m[:, 2] = 0.5 * (1.0 + c2e)
    m[:, 3] = -0.5 * ce2 * s2a
    m[:, 4] = -0.5 * s2e * fa1 * np.sin(az)
    m[:, 5] = -0.5 * s2e * fa1 * np.cos(az)
    h = np.zeros((az.shape[0], 6))
    h[:, 0] = 0.5 * (1.0 + c2a)
    h[:, 1] = 0.5 * (1.0 - c2a)
    h[:, 3] = -0.5 * s2a
    return m, h


def predicted_information(
    rays: Rays,
    origin_rel: Array,
    x_ref_rel: Array,
    cfg: EstimatorConfig,
    wts: tuple[Array, Array, Array, Array] | None = None,
) -> Array:
    """Per-ray *predicted* information ``Q_ref`` (n, 6): the weighted projectors of the
    directions from the origins to the reference position, free of the rays' direction
    noise. Summed, it is a stable estimate of ``E[A]`` used for the conditioning test.
    ``wts``: :func:`weights` of these arguments when the caller has them."""
    az, el = ray_angles(x_ref_rel - origin_rel)
    zero = np.zeros_like(az)
    m, h = projector_terms(az, el, zero, zero, False)
    w_h, w_v, _, _ = wts or weights(rays, origin_rel, x_ref_rel, cfg)
    return w_v[:, None] * m + (w_h - w_v)[:, None] * h


def pull_terms(rays: Rays, origin_rel: Array, x_ref_rel: Array, cfg: EstimatorConfig) -> Array:
    """Per ray ``tr(C_j) = 2 s_az^2 w_h0^2 c sigma^2`` (n,): the pull toward the reference
    position that an unreported shared origin error ``sigma = extra_sigma_pos_m`` leaves in
    the estimating function (``EstimatorConfig.extra_sigma_pos_m``; ``w_h0`` the horizontal
    weight before the ray's trust weight ``c``, ``C_j = tr(C_j) H~_j``, ``tr H~_j = 1``).
    Zero without that error, with uniform weights, or inside the range floor. Here
    ``w_h = 1 / (0.1^2 10^2 + 1) = 0.5``, so ``2 x 0.01 x 0.25 x 4``:

    >>> r = Rays.from_angles([[0.0, 0, 0]], [0.0], [0.0], 0.1, 0.01, 1.0, 2.0)
    >>> cfg = EstimatorConfig(extra_sigma_pos_m=2.0)
    >>> round(float(pull_terms(r, r.origin, np.array([[0, 10.0, 0]]), cfg)[0]), 12)
    0.02
    """
    n = len(rays)
    sx = float(cfg.extra_sigma_pos_m)
    if sx <= 0 or cfg.weighting != "inverse_variance" or n == 0:
        return np.zeros(n)
    s_az, _ = effective_sigmas(rays, cfg)
    w_h, _, _, _ = weights(rays, origin_rel, x_ref_rel, cfg)
    c = rays.weights_or_ones()
    w0 = w_h / np.where(c > 0, c, 1.0)
    v = x_ref_rel - origin_rel
    inside = v[:, 0] ** 2 + v[:, 1] ** 2 < cfg.min_range_m**2  # weight not origin-dependent
    return np.where(inside, 0.0, 2.0 * s_az**2 * w0**2 * c * sx**2)
