"""Evidence a second copy of a sign cannot produce: the share of the passes that had a
landmark in view that detected it.

A landmark started from the tail of the association (a pass's rays that failed the check
against their sign's landmark, false positives) stands some metres from a real sign,
mostly along the same road: every pass that drives by sees the real sign next to it, and
almost none detects it (docs/experiments/2026-12-ghosts-at-high-traffic.md). A real sign
is detected by most passes that have it in view (in the fleet simulation each frame
detects it with probability 0.8, and a pass has several frames in range).

Per unit (a pass's rays in one tile) a candidate landmark is *in view* when one of the
unit's rays starts ``range_m`` from it, within ``half_fov_deg`` of that ray's direction
(the camera looked that way at that moment), and, where its facing is known, the camera
is within ``max_view_deg`` of it (its panel faces the camera); it is *seen* when the unit
linked rays to it (which puts it in view too). Each landmark counts both. Once
``min_in_view`` units had it in view, a landmark whose share ``seen / in_view`` is below
``p_min`` with one-sided confidence ``confidence`` (the exact binomial bound) is retired:
neither a copy nor a sign that is gone keeps a share a real sign has.

Against a neighbour: a copy along its sign's line of sight gets the sign's stray rays
from a steady fraction of the passes (13-22 % in a 30-hour soak, 8-45 m from the sign:
above ``p_min`` for ever). Two signs of one class that the same passes drive by, seen
from the same side, are detected at like rates; a landmark whose share's upper bound is
under ``rel_share`` times the lower bound of such a neighbour's share (within
``rel_radius_m``, facings within ``rel_max_deg``) is retired too (counted
``retired_outshone``; :func:`outshone`).

Pitfalls: in view is judged from the rays alone (the matcher has no trajectory), so a
pass that saw nothing near the landmark does not count, for or against; ``range_m`` ends
well inside the range where every catalogue sign's box is big enough to detect
(``VehicleModel.min_box_px``), or small signs far from the road would look unseen;
occlusion is not modelled (a sign hidden from one street by a corner and seen from the
other keeps the other street's share only where its facing tells the streets apart); a
real sign detected at under half its neighbour's rate (a small panel next to a large one
of its class, one behind a tree) goes with the copies.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SightingConfig:
    """When a landmark counts as in view, and when its share retires it."""

    enabled: bool = True
    range_m: tuple[float, float] = (5.0, 25.0)
    """Horizontal distance from a ray's origin within which the landmark is in view."""
    half_fov_deg: float = 30.0
    """Largest angle between a ray's direction and the direction to the landmark."""
    max_view_deg: float = 70.0
    """Largest angle between the landmark's known facing and the direction to the camera
    (the association's ``GateConfig.facing.max_view_deg``)."""
    min_in_view: int = 20
    """Units in view before the share is tested."""
    p_min: float = 0.2
    """A real sign is detected by at least this share of the units that have it in view."""
    confidence: float = 0.999
    """One-sided confidence of the binomial bound that must lie below ``p_min``."""
    rel_share: float = 0.5
    """A landmark detected by under this fraction of the share of a same-class neighbour
    seen from the same side (both bounds at ``confidence``) is that neighbour's strays
    (:func:`outshone`; 0: off)."""
    rel_radius_m: float = 50.0
    """How far such a neighbour may be (a copy sits up to tens of metres along the line of
    sight of its sign)."""
    rel_max_deg: float = 45.0
    """Largest angle between the two facings (both known) for the comparison."""

    def __post_init__(self) -> None:
        lo, hi = self.range_m
        if not 0.0 <= lo < hi:
            raise ValueError(f"range_m: need 0 <= near < far, got {self.range_m}")
        if not 0.0 < self.p_min < 1.0 or not 0.5 < self.confidence < 1.0:
            raise ValueError("p_min in (0, 1) and confidence in (0.5, 1)")


def in_view(
    origin: Array,
    direction: Array,
    x: Array,
    facing_az: Array,
    facing_known: NDArray[np.bool_],
    cfg: SightingConfig,
) -> NDArray[np.bool_]:
    """Per landmark (``x`` (k, 3) local ENU), whether one of the rays (``origin``,
    ``direction`` (n, 3), same frame) had it in view; ``facing_az`` (k,) rad clockwise
    from North (sign toward camera), used where ``facing_known``.

    >>> o = np.zeros((1, 3)); d = np.array([[0.0, 1.0, 0.0]])
    >>> x = np.array([[0.0, 15.0, 0.0], [0.0, 60.0, 0.0], [12.0, 2.0, 0.0], [0.0, 15.0, 0.0]])
    >>> az = np.array([np.pi, np.pi, np.pi, 0.0]); known = np.array([True, True, True, True])
    >>> in_view(o, d, x, az, known, SightingConfig()).tolist()  # ahead; too far; aside; back
    [True, False, False, False]
    """
    k = len(x)
    out = np.zeros(k, bool)
    if k == 0 or len(origin) == 0:
        return out
    lo, hi = cfg.range_m
    # only landmarks within ``hi`` of the origins' bounding box can be in range (exact)
    box_lo, box_hi = origin[:, :2].min(axis=0) - hi, origin[:, :2].max(axis=0) + hi
    near = np.flatnonzero(np.all((x[:, :2] >= box_lo) & (x[:, :2] <= box_hi), axis=1))
    if near.size == 0:
        return out
    x, facing_az, facing_known = x[near], facing_az[near], facing_known[near]
    v = x[None, :, :2] - origin[:, None, :2]  # (n, k, 2) camera -> landmark
    dist = np.linalg.norm(v, axis=2)
    ok = (dist >= lo) & (dist <= hi)
    dh = direction[:, :2] / np.maximum(
        np.linalg.norm(direction[:, :2], axis=1, keepdims=True), 1e-12
    )
    cos_fov = np.einsum("nkj,nj->nk", v, dh) / np.maximum(dist, 1e-12)
    ok &= cos_fov >= math.cos(math.radians(cfg.half_fov_deg))
    # the camera seen from the landmark against its facing
    cam_az = np.arctan2(-v[..., 0], -v[..., 1])
    off = np.abs((cam_az - facing_az[None, :] + np.pi) % (2 * np.pi) - np.pi)
    ok &= ~facing_known[None, :] | (off <= math.radians(cfg.max_view_deg))
    out[near] = ok.any(axis=0)
    return out


def share_upper_bound(seen: int, n: int, confidence: float) -> float:
    """One-sided exact (Clopper-Pearson) upper bound of a binomial share: the ``p`` with
    ``P(X <= seen | n, p) = 1 - confidence`` (bisection on the binomial CDF).

    >>> round(share_upper_bound(0, 20, 0.999), 3)  # 1 - 0.001 ** (1 / 20)
    0.292
    >>> share_upper_bound(20, 20, 0.999)
    1.0
    """
    if seen >= n:
        return 1.0
    alpha = 1.0 - confidence
    lo, hi = seen / n, 1.0
    for _ in range(50):
        p = 0.5 * (lo + hi)
        if _binom_cdf(seen, n, p) > alpha:
            lo = p
        else:
            hi = p
    return hi


def _binom_cdf(s: int, n: int, p: float) -> float:
    """``P(X <= s)`` for ``X ~ Binomial(n, p)`` (log-space terms)."""
    if p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 0.0 if s < n else 1.0
    lp, lq = math.log(p), math.log1p(-p)
    terms = [
        math.lgamma(n + 1) - math.lgamma(j + 1) - math.lgamma(n - j + 1) + j * lp + (n - j) * lq
        for j in range(s + 1)
    ]
    top = max(terms)
    return min(1.0, math.exp(top) * sum(math.exp(t - top) for t in terms))


def share_lower_bound(seen: int, n: int, confidence: float) -> float:
    """One-sided exact lower bound of a binomial share (:func:`share_upper_bound` of the
    misses).

    >>> round(share_lower_bound(20, 20, 0.999), 3)
    0.708
    """
    return 1.0 - share_upper_bound(n - seen, n, confidence)


def outshone(
    seen: int, n_in_view: int, others_seen: Sequence[int], others_in_view: Sequence[int],
    cfg: SightingConfig,
) -> bool:  # fmt: skip
    """Whether a landmark's share is binomially below ``rel_share`` times the share of one
    of ``others`` (its same-class neighbours seen from the same side, the caller's choice):
    two signs of one class that the same passes drive by are detected at like rates, and a
    landmark detected at a fraction of its neighbour's rate is made of that neighbour's
    stray rays (a copy along its line of sight; issue 18's ghosts).

    >>> cfg = SightingConfig()
    >>> outshone(44, 212, [420], [500], cfg), outshone(300, 500, [450], [500], cfg)
    (True, False)
    """
    if cfg.rel_share <= 0.0 or n_in_view < cfg.min_in_view:
        return False
    best = 0.0
    for s_o, n_o in zip(others_seen, others_in_view, strict=True):
        if n_o >= cfg.min_in_view:
            best = max(best, share_lower_bound(int(s_o), int(n_o), cfg.confidence))
    if seen >= cfg.rel_share * best * n_in_view:
        return False  # the bound is never below the share itself
    return share_upper_bound(seen, n_in_view, cfg.confidence) < cfg.rel_share * best


def unseen(seen: int, n_in_view: int, cfg: SightingConfig) -> bool:
    """Whether a landmark's share is binomially below ``p_min`` (see the module)."""
    if n_in_view < cfg.min_in_view or seen >= cfg.p_min * n_in_view:
        return False  # the bound is never below the share itself: no need to solve it
    return share_upper_bound(seen, n_in_view, cfg.confidence) < cfg.p_min
