"""Whether a mapped sign still stands: its existence as clamped log-odds, updated once per
pass that had it in view, from whether the pass detected it (issue 21).

A pass that had the landmark in view in ``n`` frames detects a standing sign with
probability ``P_d(n) = p_detect * min(1, n / full_frames)`` (fewer frames in view, weaker
evidence either way) and reports a sign that is gone as seen with probability
``p_false`` (another sign of its class at its place, a false detection). The log-odds
``L = log P(stands) / P(gone)`` then move by

    seen:      + log(P_d / p_false)
    not seen:  + log((1 - P_d) / (1 - p_false))

and are clamped to ``[l_min, l_max]`` (an occupancy-grid rule: a long history must not
make a sign immune to being taken down, nor a revoked one deaf to being put back before
its revocation is final). Status: ``confirmed`` at or above ``l_confirmed``, ``revoked``
at or below ``l_revoked`` (final: the id is never reused), ``doubtful`` between.

Invariant: a pass counts once per landmark (the caller keys evidence by (vehicle, pass)).
Pitfall: passes are not independent when one vehicle reports many of them (a blind
camera): the caller bounds a vehicle's negative evidence (issue 21 point 5).

>>> cfg = ExistenceConfig()
>>> passes_to_revoke(cfg, frames=cfg.full_frames)  # from the cap, every pass a miss
5
>>> [status(l_after([False] * k, cfg.l_max, cfg), cfg) for k in (4, 5)]
['doubtful', 'revoked']
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

CONFIRMED, DOUBTFUL, REVOKED = "confirmed", "doubtful", "revoked"


@dataclass(frozen=True)
class ExistenceConfig:
    p_detect: float = 0.9
    """A pass with the sign fully in view detects a standing sign with this probability."""
    full_frames: int = 10
    """Frames in view that make a full look (fewer: ``P_d`` scaled down)."""
    p_false: float = 0.02
    """A pass reports a sign that is gone as seen (a false or another sign's detection)."""
    l_max: float = 6.9
    """Cap of the log-odds (0.999): with the defaults five missed full looks in a row take
    a sign at the cap to revoked; a standing sign missed one pass in ten is then revoked
    with probability about 1e-5 a pass (:func:`revocation_probability`)."""
    l_min: float = -4.6
    l_confirmed: float = 1.4
    """At or above: confirmed (0.8)."""
    l_revoked: float = -2.9
    """At or below: revoked, for good (0.05)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.p_false < self.p_detect < 1.0:
            raise ValueError("existence: need 0 < p_false < p_detect < 1")
        if not self.l_min <= self.l_revoked < self.l_confirmed <= self.l_max:
            raise ValueError("existence: need l_min <= l_revoked < l_confirmed <= l_max")
        if self.full_frames < 1:
            raise ValueError("existence: full_frames must be at least 1")


def p_detect(frames: ArrayLike, cfg: ExistenceConfig) -> NDArray[np.float64]:
    """Probability that a pass with the sign in view in ``frames`` frames detects it."""
    n = np.asarray(frames, float)
    return cfg.p_detect * np.clip(n / cfg.full_frames, 0.0, 1.0)


def step(seen: ArrayLike, frames: ArrayLike, cfg: ExistenceConfig) -> NDArray[np.float64]:
    """The log-odds change of one pass per landmark (0 where nothing was in view)."""
    pd = np.maximum(p_detect(frames, cfg), cfg.p_false)  # no evidence below the false rate
    hit = np.log(pd / cfg.p_false)
    miss = np.log((1.0 - pd) / (1.0 - cfg.p_false))
    return np.where(np.asarray(seen, bool), hit, miss)


def update(
    l: ArrayLike, seen: ArrayLike, frames: ArrayLike, cfg: ExistenceConfig
) -> NDArray[np.float64]:
    """Log-odds after one pass each (revoked ones stay where they are: final)."""
    l0 = np.asarray(l, float)
    new = np.clip(l0 + step(seen, frames, cfg), cfg.l_min, cfg.l_max)
    return np.where(l0 <= cfg.l_revoked, l0, new)


def l_after(
    seen: Iterable[bool], l0: float, cfg: ExistenceConfig, frames: int | None = None
) -> float:
    """Log-odds after a sequence of passes (each with ``frames``, default a full look)."""
    l = np.array([l0])
    for s in seen:
        l = update(l, [s], [cfg.full_frames if frames is None else frames], cfg)
    return float(l[0])


def status(l: float, cfg: ExistenceConfig) -> str:
    if l <= cfg.l_revoked:
        return REVOKED
    return CONFIRMED if l >= cfg.l_confirmed else DOUBTFUL


def passes_to_revoke(cfg: ExistenceConfig, frames: int) -> int:
    """Passes, all misses with ``frames`` in view, that take a landmark at the cap to
    revoked (a large number where a miss is no evidence)."""
    miss = float(step([False], [frames], cfg)[0])
    if miss >= 0.0:
        return 10**9
    return max(1, math.ceil((cfg.l_revoked - cfg.l_max) / miss - 1e-12))


def revocation_probability(
    cfg: ExistenceConfig, p_seen: float, passes: int, l0: float | None = None, grid: int = 2001
) -> float:
    """Probability that a landmark starting at ``l0`` (default the cap) is revoked within
    ``passes`` full-look passes that each see it with probability ``p_seen`` (exact up to
    the grid: a Markov chain over the clamped log-odds, revoked absorbing)."""
    x = np.linspace(cfg.l_min, cfg.l_max, grid)
    dx = x[1] - x[0]
    hit, miss = step([True, False], [cfg.full_frames] * 2, cfg)
    prob = np.zeros(grid)
    prob[round(((cfg.l_max if l0 is None else l0) - cfg.l_min) / dx)] = 1.0
    absorbed = 0.0
    for _ in range(passes):
        nxt = np.zeros(grid)
        for d, p in ((hit, p_seen), (miss, 1.0 - p_seen)):
            to = np.clip(
                np.round((np.clip(x + d, cfg.l_min, cfg.l_max) - cfg.l_min) / dx), 0, grid - 1
            )
            np.add.at(nxt, to.astype(int), p * prob)
        gone = x <= cfg.l_revoked + 1e-9
        absorbed += float(nxt[gone].sum())
        nxt[gone] = 0.0
        prob = nxt
    return absorbed
