"""The vehicle's pose at a camera frame's capture time, interpolated from the GNSS fixes.

GNSS fixes and camera frames come at their own rates and times (a receiver at 1-10 Hz, a
camera at 10-30 Hz, fixes missing now and then). The pose at a frame is interpolated
from the two fixes around it (:func:`bracket`): the position linearly, in a local
Cartesian frame; the heading linearly on the circle (the short way round).

**How wrong is a linear interpolant** (the growth of the sigmas with the gap). Between
two fixes at ``t_a < t_b`` the vehicle's position ``p(t)`` has an acceleration the fixes
do not tell; model it per axis as unknown but constant over the interval,
``p'' = a ~ N(0, sigma_a^2)``. The linear interpolant ``L`` through ``p(t_a)``, ``p(t_b)``
then errs by the interpolation remainder of a quadratic, exactly:

    p(t) - L(t) = a / 2 * (t - t_a) * (t - t_b)

so its standard deviation is ``sigma_a / 2 * |tau_a * tau_b|`` with ``tau_a = t - t_a``,
``tau_b = t - t_b`` (:func:`motion_sigma`): zero at a fix, ``sigma_a g^2 / 8`` in the middle
of a gap ``g`` (1 Hz, 2 m/s^2: 0.25 m; 5 Hz: 0.01 m). The same formula holds outside
``[t_a, t_b]`` (extrapolation, where it grows faster). The heading gets the same with an
unmodelled yaw acceleration. Turning at a corner (11 m/s on a 20 m radius, 6 m/s^2
across the path) is the worst case; ``sigma_a`` is a 1-sigma figure, not a bound.

**The fixes' own errors** at the interpolated time: ``(1 - w) e_a + w e_b`` with the
weight ``w`` of fix ``b``. Consecutive fixes share most of their error (a receiver's bias
drifts slowly), and for any correlation the standard deviation is at most
``|1 - w| sigma_a + |w| sigma_b`` (:func:`interpolate_sigma`, exact for fully correlated
errors inside the interval, and an upper bound outside it, where ``w`` leaves [0, 1]).
The two terms are independent and add in quadrature. For the heading the bound is too
wide to use: the map's bias compensation takes a ray's angular variance as told, and at the
paper's 0.35 rad of white heading error the bound over-corrects by tens of metres. There a
fix's error is taken as a shared part plus a white part whose share :func:`white_share`
estimates from the pass's own fixes, and :func:`interpolate_sigma` combines the two
(docs/experiments/2026-12-interpolated-sigma-overcompensation.md).

**What a view of a sign shares** (:func:`view_shares`). Receivers report their total
errors (Android's ``accuracy``, ``bearingAccuracyDegrees``), most of which a pass holds
for minutes. The bias compensation must see only the part that changes between the rays
of one view (2-6 s): what lasts a whole view moves the rays together and, compensated as
if white, puts every landmark beyond its sign. The share of each claimed sigma that
changes within ``PoseTiming.view_lag_s`` is measured from the fixes' second differences
at that lag over straight driving, so the caller reports totals and the split comes from
the data (docs/experiments/2026-12-shared-heading-compensation.md, Finding 4).

**What the fixes show of the acceleration** (``PoseTiming.observed_turns``, on by
default). ``sigma_a`` is then a floor: where the fixes
themselves show the vehicle turning, the interval's acceleration scale is taken from them
(:func:`observed_accels`): the yaw acceleration from the second differences of the fix
headings at the interval's two ends (the larger), the acceleration across the path from
its yaw rate times its chord speed, ``|omega| |p_b - p_a| / (t_b - t_a)`` (on a circle:
``v^2 / R``, the quadratic term that the remainder above is exact for). They add to the
floors in quadrature. The estimates carry the fixes' noise, so a yaw rate or acceleration
counts only beyond :data:`TURN_SIGNIFICANCE` (3) standard deviations of what the fixes'
claimed heading noise makes of it, less that noise in quadrature (FLEET's 0.01 rad at
5 Hz: 0.6 rad/s^2 of noise, against about 7 rad/s^2 at the start of a corner; the paper's
0.35 rad: 21 rad/s^2, so no turn counts there); they are there for the corners, where a
constant floor is wrong by an order of magnitude. The yaw floor itself is at most that
threshold (:func:`hidden_yaw_accel`): a larger yaw acceleration would have been seen.

**Not extrapolated**: a frame farther than ``max_gap_s`` from its nearest fix (inside the
fixes' span, or before the first or after the last) has no pose (:func:`reachable`); the
caller drops and counts it. Within ``max_gap_s`` beyond the span, the two end fixes'
line is used, with the sigmas above.

>>> br = bracket(np.array([0.0, 1.0, 2.0]), np.array([0.5, 2.0]))
>>> br.ia.tolist(), br.ib.tolist(), br.w.tolist()
([0, 1], [1, 2], [0.5, 1.0])
>>> motion_sigma(br, 2.0).tolist()  # sigma_a g^2 / 8 in the middle of a 1 s gap
[0.25, 0.0]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


TURN_SIGNIFICANCE = 3.0
"""A turn the fixes show counts (:func:`observed_accels`) only beyond this many standard
deviations of what their claimed heading noise makes of it."""


@dataclass(frozen=True)
class PoseTiming:
    """How a frame's pose is interpolated from the fixes around it (module docstring)."""

    max_gap_s: float = 1.0
    """A frame farther than this from its nearest fix has no pose (dropped, not
    extrapolated), s."""
    accel_sigma_mps2: float = 2.0
    """Unmodelled horizontal acceleration per axis, m/s^2 (1 sigma; urban driving)."""
    accel_v_sigma_mps2: float = 0.5
    """Unmodelled vertical acceleration, m/s^2 (road grade changes)."""
    yaw_accel_sigma_radps2: float = 0.5
    """Unmodelled yaw acceleration, rad/s^2 (entering a corner: 0.7 rad/s in 1-2 s). With
    ``observed_turns`` and claimed heading sigmas, at most what the fixes would not have
    shown (:func:`hidden_yaw_accel`): at 1 Hz and 0.57 deg that is 0.07 rad/s^2, where the
    0.5 floor claimed 3.6 deg of heading error mid-gap on every straight, which the bias
    compensation then removed from rays that never had it (with exact GNSS at 1 Hz the
    landmarks stood 1.6 m beyond their signs; docs/experiments/2026-12-one-hertz-gnss.md)."""
    view_lag_s: float = 2.0
    """Lag of :func:`view_shares`, s: the part of the heading error that changes within
    this long counts as varying between the rays of one view of a sign (a view lasts 2-6
    s); what lasts longer, the pass shares. 0: no split, every ray claims the receiver's
    heading sigma whole."""
    observed_turns: bool = True
    """Raise the acceleration scales by what the fixes show of each interval's turn
    (:func:`observed_accels`). At a corner's start the heading interpolated between two
    5 Hz fixes is off by up to a quarter of the interval's turn; without this term the
    rays taken at yaw rates over 0.1 rad/s claimed 0.1-0.2 deg and were off 0.75-1.9 deg
    (z RMS 5-12; with it 1.4-1.6): docs/experiments/2026-12-gsdc-course-over-ground.md.
    (It was off while the simulator's heading turned slowly over the straights.)"""

    def __post_init__(self) -> None:
        for name in ("max_gap_s", "accel_sigma_mps2", "accel_v_sigma_mps2",
                     "yaw_accel_sigma_radps2", "view_lag_s"):  # fmt: skip
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(f"PoseTiming.{name}: must be finite and >= 0, got {v!r}")


def check_increasing(t: ArrayLike, name: str) -> Array:
    """``t`` as a float array; ValueError naming ``name`` unless finite and strictly
    increasing."""
    v = np.asarray(t, float).reshape(-1)
    if not np.isfinite(v).all():
        raise ValueError(f"{name}: must be finite (row {int(np.flatnonzero(~np.isfinite(v))[0])})")
    bad = np.flatnonzero(np.diff(v) <= 0.0)
    if bad.size:
        k = int(bad[0])
        a, b = float(v[k]), float(v[k + 1])
        raise ValueError(f"{name}: must be strictly increasing, row {k + 1} ({b!r}) follows {a!r}")
    return v


@dataclass(frozen=True)
class Bracket:
    """Per query time: the two fixes it is interpolated from and the weight of ``ib``."""

    ia: IntArray
    ib: IntArray
    w: Array
    """Weight of fix ``ib`` (1 - w of ``ia``); outside [0, 1] beyond the fixes' span."""
    tau_a: Array
    tau_b: Array
    """``t - t[ia]``, ``t - t[ib]``, s."""

    @property
    def nearest_s(self) -> Array:
        """Time to the nearest fix, s."""
        return np.minimum(np.abs(self.tau_a), np.abs(self.tau_b))


def bracket(fix_t: ArrayLike, t: ArrayLike) -> Bracket:
    """The fixes around each time ``t`` (``fix_t`` strictly increasing, not checked here:
    :func:`check_increasing`). Before the first fix: the first two; after the last: the last
    two; one fix only: that fix, weight 0."""
    ft = np.asarray(fix_t, float)
    q = np.asarray(t, float).reshape(-1)
    n = ft.size
    if n == 0:
        raise ValueError("GnssFixes.t: no fixes to interpolate from")
    if n == 1:
        z = np.zeros(q.size, np.int64)
        tau = q - ft[0]
        return Bracket(z, z, np.zeros(q.size), tau, tau)
    ib = np.clip(np.searchsorted(ft, q, side="right"), 1, n - 1).astype(np.int64)
    ia = ib - 1
    ta, tb = ft[ia], ft[ib]
    return Bracket(ia, ib, (q - ta) / (tb - ta), q - ta, q - tb)


def reachable(br: Bracket, timing: PoseTiming) -> NDArray[np.bool_]:
    """Query times with a fix within ``max_gap_s`` (and, with one fix only, at it)."""
    if bool((br.ia == br.ib).all()):
        return br.nearest_s <= 1e-9
    return br.nearest_s <= timing.max_gap_s


def interpolate(br: Bracket, values: ArrayLike) -> Array:
    """Linear interpolation (and, beyond the span, extrapolation) of per-fix ``values``
    (n, ...) at the bracketed times."""
    v = np.asarray(values, float)
    w = br.w.reshape((-1,) + (1,) * (v.ndim - 1))
    return (1.0 - w) * v[br.ia] + w * v[br.ib]


def wrap_angle(a: ArrayLike) -> Array:
    """Angles (rad) wrapped to [-pi, pi): the short way round."""
    return (np.asarray(a, float) + np.pi) % (2.0 * np.pi) - np.pi


def interpolate_angle(br: Bracket, angle_rad: ArrayLike) -> Array:
    """Per-fix angles interpolated the short way round the circle, wrapped to [0, 2 pi).

    >>> br = bracket(np.array([0.0, 1.0]), np.array([0.5]))
    >>> np.degrees(interpolate_angle(br, np.radians([350.0, 10.0]))).round(9).tolist()
    [0.0]
    """
    a = np.asarray(angle_rad, float)
    d = wrap_angle(a[br.ib] - a[br.ia])
    return (a[br.ia] + br.w * d) % (2.0 * np.pi)


def interpolate_sigma(br: Bracket, sigma: ArrayLike, white: float = 0.0) -> Array:
    """Standard deviation of ``(1 - w) e_a + w e_b`` when a share ``white`` of each fix's
    sigma is white noise and the rest an error consecutive fixes share (a bias):
    ``sqrt((1 - r^2) c^2 + r^2 u^2)`` with ``c = |1 - w| sigma_a + |w| sigma_b`` (shared) and
    ``u = hypot((1 - w) sigma_a, w sigma_b)`` (white). ``white=0`` is the upper bound for
    any correlation (module docstring); :func:`white_share` estimates it from the fixes.

    >>> br = bracket(np.array([0.0, 1.0]), np.array([0.5]))
    >>> interpolate_sigma(br, [1.0, 1.0]).tolist()  # shared: the bound
    [1.0]
    >>> interpolate_sigma(br, [1.0, 1.0], 1.0).round(4).tolist()  # white
    [0.7071]
    """
    s = np.asarray(sigma, float)
    shared = np.abs(1.0 - br.w) * s[br.ia] + np.abs(br.w) * s[br.ib]
    r2 = float(np.clip(white, 0.0, 1.0)) ** 2
    if r2 == 0.0:
        return shared
    alone = np.hypot((1.0 - br.w) * s[br.ia], br.w * s[br.ib])
    return np.sqrt((1.0 - r2) * shared**2 + r2 * alone**2)


WHITE_SHARE_MIN_FIXES = 10
""":func:`white_share` needs this many fixes; with fewer it gives 0 (the upper bound)."""


def white_share(
    t: ArrayLike,
    values: ArrayLike,
    sigma: ArrayLike,
    angle: bool = False,
    min_fixes: int = WHITE_SHARE_MIN_FIXES,
) -> float:
    """The share of the reported ``sigma`` (per fix) that is white noise, from the fixes
    themselves: per interior fix the second divided difference of ``values`` (n, or n x k,
    pooled over columns; ``angle``: wrapped, rad) normalised to the variance of one fix's
    white error, ``z = (dv_2 / h_2 - dv_1 / h_1) / sqrt(1/h_1^2 + (1/h_1 + 1/h_2)^2 +
    1/h_2^2)``; its robust scale (1.4826 median |z|; turns and accelerations are the
    outliers) over the median reported sigma, in [0, 1]. A bias consecutive fixes share
    cancels in the differences. Fewer than ``min_fixes``: 0 (the upper bound).

    >>> rng = np.random.default_rng(0)
    >>> t = np.arange(200) * 0.2
    >>> white = 10.0 * t + rng.normal(0.0, 1.0, 200)  # 1 m white, reported 1 m
    >>> 0.8 < white_share(t, white, np.ones(200)) <= 1.0
    True
    >>> round(white_share(t, 10.0 * t + 3.0, np.ones(200)), 6)  # a bias only
    0.0
    """
    tt = np.asarray(t, float).reshape(-1)
    ref = float(np.median(np.asarray(sigma, float))) if tt.size else 0.0
    if tt.size < max(min_fixes, 3) or not (np.isfinite(ref) and ref > 0.0):
        return 0.0
    v = np.asarray(values, float).reshape(tt.size, -1)
    h1 = (tt[1:-1] - tt[:-2])[:, None]
    h2 = (tt[2:] - tt[1:-1])[:, None]
    dv = np.diff(v, axis=0)
    if angle:
        dv = wrap_angle(dv)
    d2 = dv[1:] / h2 - dv[:-1] / h1
    z = d2 / second_difference_scale(h1, h2)
    return float(np.clip(1.4826 * np.median(np.abs(z)) / ref, 0.0, 1.0))


STRAIGHT_K = 2.0
""":func:`view_shares` uses a fix's lag triple only where the heading turns by less than
this many standard deviations of the claimed noise over the triple (driving straight)."""


def straight_lag_triples(
    t: Array, heading_rad: Array, heading_sigma: Array, lag_s: float
) -> tuple[IntArray, IntArray, IntArray] | None:
    """Per fix ``i`` the fixes ``a``, ``c`` nearest to ``lag_s`` before and after it (no
    farther than 1.5 ``lag_s``), kept only where the heading turns by less than
    :data:`STRAIGHT_K` times the claimed noise of that turn (driving straight). None: none.
    For independent errors of equal variance the first difference ``e_c - e_a`` and the
    second ``e_c - 2 e_i + e_a`` are uncorrelated, so the selection does not bias the
    second differences' scale."""
    n = t.size
    if n < 3 or lag_s <= 0.0:
        return None
    a = np.searchsorted(t, t - lag_s, side="right") - 1  # last fix at or before t - lag
    c = np.searchsorted(t, t + lag_s)  # first fix at or after t + lag
    b = np.arange(n)
    ok = (a >= 0) & (c < n)
    a, b, c = a[ok], b[ok], c[ok]
    ok = (t[b] - t[a] <= 1.5 * lag_s) & (t[c] - t[b] <= 1.5 * lag_s)
    turn = wrap_angle(heading_rad[c] - heading_rad[a])
    ok &= np.abs(turn) < STRAIGHT_K * np.hypot(heading_sigma[a], heading_sigma[c])
    if not ok.any():
        return None
    return a[ok], b[ok], c[ok]


def view_shares(
    t: ArrayLike,
    heading_rad: ArrayLike,
    heading_sigma: ArrayLike,
    lag_s: float,
    xyz: ArrayLike | None = None,
    sigma_h: ArrayLike | None = None,
    sigma_v: ArrayLike | None = None,
    min_triples: int = 10,
) -> tuple[float, float, float]:
    """The shares of the claimed sigmas (per fix) that change within ``lag_s`` seconds,
    from the fixes themselves: of the heading (rad), and with ``xyz`` (n x 3, m) of the
    horizontal position (``sigma_h``, m per axis) and of the height (``sigma_v``).

    Over the fixes' :func:`straight_lag_triples` the normalised second divided difference
    ``z`` of :func:`white_share` (of the heading; of the position across the direction of
    travel, where driving straight has none of its own; of the height): an error that
    lasts much longer than ``lag_s`` cancels in it, one that changes within it counts whole
    (white noise per fix, or a course error that holds for a second and then jumps, as a
    1 Hz receiver's does). Bends would count as noise at these lags, hence the straight
    triples only. A share is the robust scale of ``z`` (1.4826 median ``|z|``) over the
    median claim, in [0, 1]; 1 (the claim whole) with fewer than ``min_triples`` triples,
    or for a position not given.

    A per-pass bias cancels; white noise does not:

    >>> rng = np.random.default_rng(1)
    >>> t = np.arange(300) * 0.2
    >>> s = np.full(300, 0.02)
    >>> round(view_shares(t, np.full(300, 0.03), s, 2.0)[0], 6)
    0.0
    >>> 0.8 < view_shares(t, rng.normal(0.0, 0.02, 300), s, 2.0)[0] <= 1.0
    True
    >>> track = np.column_stack([np.full(300, 5.0), 10.0 * t, np.full(300, 2.0)])  # biased
    >>> [round(r, 6) for r in view_shares(t, np.zeros(300), s, 2.0, track, s, s)[1:]]
    [0.0, 0.0]
    """
    tt = np.asarray(t, float).reshape(-1)
    psi = np.asarray(heading_rad, float).reshape(-1)
    s_psi = np.asarray(heading_sigma, float).reshape(-1)
    tri = straight_lag_triples(tt, psi, s_psi, lag_s) if tt.size else None
    if tri is None or tri[0].size < min_triples:
        return 1.0, 1.0, 1.0
    a, b, c = tri
    h1, h2 = tt[b] - tt[a], tt[c] - tt[b]
    scale = second_difference_scale(h1, h2)

    def share(d2: Array, sigma: ArrayLike | None) -> float:
        ref = float(np.median(np.asarray(sigma, float))) if sigma is not None else 0.0
        if not (np.isfinite(ref) and ref > 0.0):
            return 1.0
        return float(np.clip(1.4826 * np.median(np.abs(d2 / scale)) / ref, 0.0, 1.0))

    r_psi = share(wrap_angle(psi[c] - psi[b]) / h2 - wrap_angle(psi[b] - psi[a]) / h1, s_psi)
    if xyz is None:
        return r_psi, 1.0, 1.0
    p = np.asarray(xyz, float)
    dd = (p[c] - p[b]) / h2[:, None] - (p[b] - p[a]) / h1[:, None]
    across = dd[:, 0] * np.cos(psi[b]) - dd[:, 1] * np.sin(psi[b])
    return r_psi, share(across, sigma_h), share(dd[:, 2], sigma_v)


def second_difference_scale(
    h1: ArrayLike, h2: ArrayLike, s0: ArrayLike = 1.0, s1: ArrayLike = 1.0, s2: ArrayLike = 1.0
) -> Array:
    """Standard deviation of the second divided difference ``(v_2 - v_1) / h_2 - (v_1 -
    v_0) / h_1`` when the three values carry independent errors of std ``s0, s1, s2``
    (intervals ``h1``, ``h2``): ``sqrt((s0 / h1)^2 + (s1 (1/h1 + 1/h2))^2 + (s2 / h2)^2)``.

    >>> float(second_difference_scale(1.0, 1.0))  # sqrt(1 + 4 + 1)
    2.449489742783178
    """
    h1, h2 = np.asarray(h1, float), np.asarray(h2, float)
    return np.sqrt((s0 / h1) ** 2 + (np.multiply(s1, 1.0 / h1 + 1.0 / h2)) ** 2 + (s2 / h2) ** 2)


def observed_accels(
    t: ArrayLike,
    heading_rad: ArrayLike,
    xy: ArrayLike,
    heading_sigma: ArrayLike | None = None,
    k_sigma: float = TURN_SIGNIFICANCE,
) -> tuple[Array, Array]:
    """Per interval between consecutive fixes (n - 1): the yaw acceleration (rad/s^2) and
    the acceleration across the path (m/s^2) the fixes show (module docstring); zeros with
    fewer than 3 (yaw) or 2 fixes. With ``heading_sigma`` (rad, per fix: the claimed
    heading noise) a yaw rate or yaw acceleration is kept only where it exceeds
    ``k_sigma`` times what that noise alone makes of it, less that noise in quadrature
    (the paper's 0.35 rad of white heading noise at 5 Hz makes 2.5 rad/s of yaw rate and
    21 rad/s^2 of yaw acceleration out of nothing).

    >>> t = np.arange(5.0)
    >>> psi = np.radians([0.0, 0.0, 10.0, 20.0, 20.0])  # a turn of 20 deg over 2 s
    >>> xy = np.column_stack([np.zeros(5), 10.0 * t])
    >>> yaw, across = observed_accels(t, psi, xy)
    >>> np.degrees(yaw).round(6).tolist(), across.round(3).tolist()
    ([10.0, 10.0, 10.0, 10.0], [0.0, 1.745, 1.745, 0.0])
    """
    tt = np.asarray(t, float)
    n = tt.size
    if n < 2:
        return np.zeros(0), np.zeros(0)
    dt = np.diff(tt)
    omega = wrap_angle(np.diff(np.asarray(heading_rad, float))) / dt
    speed = np.linalg.norm(np.diff(np.asarray(xy, float), axis=0), axis=-1) / dt
    s = None if heading_sigma is None else np.broadcast_to(np.asarray(heading_sigma, float), (n,))
    if s is not None:  # the yaw rate white heading noise makes: sqrt(s_a^2 + s_b^2) / dt
        omega = _significant(omega, np.hypot(s[:-1], s[1:]) / dt, k_sigma)
    across = np.abs(omega) * speed
    if n < 3:
        return np.zeros(n - 1), across
    at_fix = np.zeros(n)
    mid = (tt[2:] - tt[:-2]) / 2.0
    at_fix[1:-1] = np.abs(np.diff(omega)) / mid
    if s is not None:
        noise = second_difference_scale(dt[:-1], dt[1:], s[:-2], s[1:-1], s[2:]) / mid
        at_fix[1:-1] = _significant(at_fix[1:-1], noise, k_sigma)
    at_fix[0], at_fix[-1] = at_fix[1], at_fix[-2]
    return np.maximum(at_fix[:-1], at_fix[1:]), across


def hidden_yaw_accel(
    t: ArrayLike, heading_sigma: ArrayLike, k_sigma: float = TURN_SIGNIFICANCE
) -> Array:
    """Per interval between consecutive fixes (n - 1): the largest yaw acceleration the
    fixes could show without :func:`observed_accels` counting it, rad/s^2: ``k_sigma``
    times the noise their claimed heading sigma puts into a yaw acceleration (the larger
    of the interval's two ends). What the fixes hide is at most this; with fewer than 3
    fixes, infinite (nothing is seen).

    >>> hidden_yaw_accel(np.arange(4.0), np.full(4, 0.01)).round(4).tolist()  # 1 Hz
    [0.0735, 0.0735, 0.0735]
    """
    tt = np.asarray(t, float)
    n = tt.size
    if n < 3:
        return np.full(max(n - 1, 0), np.inf)
    s = np.broadcast_to(np.asarray(heading_sigma, float), (n,))
    dt = np.diff(tt)
    mid = (tt[2:] - tt[:-2]) / 2.0
    at_fix = np.zeros(n)
    at_fix[1:-1] = k_sigma * second_difference_scale(dt[:-1], dt[1:], s[:-2], s[1:-1], s[2:]) / mid
    at_fix[0], at_fix[-1] = at_fix[1], at_fix[-2]
    return np.maximum(at_fix[:-1], at_fix[1:])


def _significant(x: Array, noise: Array, k_sigma: float) -> Array:
    """``x`` less ``noise`` in quadrature where ``|x| > k_sigma noise``, else 0 (sign kept)."""
    keep = np.abs(x) > k_sigma * noise
    return np.where(keep, np.sign(x) * np.sqrt(np.maximum(x * x - noise * noise, 0.0)), 0.0)


def motion_sigma(br: Bracket, accel_sigma: float | Array) -> Array:
    """Standard deviation of the linear interpolant's error under an unmodelled constant
    acceleration of std ``accel_sigma`` (a number, or one per query time):
    ``accel_sigma / 2 * |tau_a tau_b|`` (module docstring). With one fix (no interpolant)
    it is 0 at the fix and unbounded elsewhere: such times are not :func:`reachable`."""
    return 0.5 * accel_sigma * np.abs(br.tau_a * br.tau_b)
