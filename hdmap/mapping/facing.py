"""Which way a landmark's sign is seen from: its *facing*, from its rays' viewing directions.

A ray's **viewing azimuth** is the horizontal azimuth (clockwise from North) from the sign
toward the camera, i.e. of ``-direction``: ``theta = atan2(-d_E, -d_N)``. A landmark keeps
the sum of its rays' horizontal unit directions ``view = sum_j (d_E, d_N)_j / |(d_E, d_N)_j|``
(camera toward sign; :attr:`hdmap.mapping.landmarks.Landmark.view`) and a ray count, so
``C = sum cos theta = -view_N``, ``S = sum sin theta = -view_E``: O(1) state, no per-ray
storage, and two landmarks' sums add when they merge.

Estimate (circular mean of the viewing azimuths, a von Mises / wrapped-normal model):

- ``facing = atan2(S, C)``, the mean direction;
- mean resultant length ``R = |(C, S)| / n``, population length ``rho`` estimated
  without its small-sample bias (``E[R^2] = rho^2 + (1 - rho^2) / n``, so
  ``rho^2 ~ (n R^2 - 1) / (n - 1)``, clipped to (0, 1]), circular standard deviation
  ``spread = sqrt(-ln rho^2)`` (for a wrapped normal of sigma ``s`` exactly ``s``, since
  ``rho = exp(-s^2 / 2)``);
- ``sigma = spread / sqrt(n_eff)``, the standard error of the mean direction. For ``n``
  independent angles the delta method gives ``Var = (1 - E cos 2(theta - mu)) / (2 n R^2)``,
  which for a wrapped normal is ``(1 - exp(-2 s^2)) / (2 n exp(-s^2))``: ``s^2 / n`` to
  first order, 1.005 times ``spread^2 / n`` at ``s`` = 0.5 rad and 1.17 times at 1 rad (so
  ``sigma`` is at most 8 % short below 1 rad of spread). The rays of one pass are one
  trajectory past the sign, not independent looks, so the services use the landmark's
  passes as ``n_eff`` (never more than its rays).

**What this is not.** A car sees a roadside sign from the road ahead of it, 5-70 degrees
off the panel's normal and always on the same side of it (the road's side), so the
facing is "the direction it is seen from", biased from the normal by the mean viewing
offset (fleet simulation, exact camera positions: mean 19.5 degrees, p95 56, the large
ones signs seen from a crossing street; docs/experiments/2026-12-facing.md).
It is published under that name; a map that needs the panel normal must correct for the
road geometry.

**Gate** (:func:`ray_compatible`). A panel is readable within ``V`` (70-80 degrees) of its
normal ``N``, so every ray of the sign, and therefore their mean, lies within ``V`` of
``N``; and a car stream sees a roadside sign from one side of its normal (the road's), so
a new ray of the sign from that side is within ``V`` of the mean (rays on ``[N, N + V]``,
mean inside that interval). The gate refuses a ray whose viewing azimuth is more than
``V + k sigma`` from a known facing: ``V`` = ``max_view_deg`` = 70 (the panel's cone; in
the fleet simulation, 80 passes over the evaluation town, 99.8 % of the true rays are
within 70 degrees of their sign's mean viewing direction, p99 53, the rest from signs
seen from two streets), ``k sigma`` (``k_sigma`` = 1) the facing's own uncertainty, which
matters only while it rests on one or two passes. Not 2 V: two signs at a corner facing
streets 90 degrees apart are seen from directions 75-95 degrees apart (each sign's far
rays, a few degrees off its normal on the road's side; the test corner of
``tests/unit/test_facing.py``), and their far rays are where the position gate is
weakest: at ``V`` = 80 and ``k`` = 3 the second sign's first pass joined the first's
landmark and the two became one, as in the issue. A ray from the far side of the normal
past ``V - |facing - N|`` is refused too: it waits in the pending pool, at worst starting
a landmark of its own (merged back if the facings are compatible, below).

**Merge** (:func:`facings_compatible`): two landmarks of one sign estimate the same
facing up to their sigmas and to which parts of the cone their rays came from, so two
known facings more than ``max_deg + k sqrt(sigma_a^2 + sigma_b^2)`` apart are two signs,
unless they stand at one place (``same_place_m``): a sign seen from two streets (a
junction's) gets a second landmark from the second street's rays, which the ray gate
keeps off the first, at the same place; merged, the kept landmark takes the other's
facing as a second one (:attr:`Facing.second`; its mean alone stays the busier street's)
and both streams pass the gate. At one place the limit is ``2 V``: one panel is never
seen from directions farther apart, two panels back to back (180 degrees) are two signs.

A landmark with fewer than ``min_rays`` rays has no facing (``known`` False) and imposes no
constraint.

>>> import numpy as np
>>> d = np.array([[0.0, 1.0, 0.0], [0.1, 1.0, 0.0]])  # looking North: seen from the South
>>> f = facing_from_sums(view_vectors(d).sum(0)[None], np.array([2]), np.array([2]), 2)
>>> round(float(np.degrees(f.azimuth[0])), 2), bool(f.known[0])
(182.86, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FacingConfig:
    """When a facing is known and how far a ray or another landmark may be from it."""

    min_rays: int = 3
    """Rays a landmark needs before its facing constrains anything."""
    max_view_deg: float = 70.0
    """``V``: half-width of the cone a panel is read within, around its normal (the gate
    refuses rays farther than ``V + k_sigma * sigma`` from the facing; module docstring)."""
    k_sigma: float = 1.0
    """Standard errors of the facing(s) added to the gates (the ray gate and the merge
    test): one, since ``sigma`` counts a landmark's passes as its independent looks but the
    same lane gives nearly the same sweep of angles every pass."""
    same_place_m: float = 3.0
    """Two landmarks of a class closer than this (horizontally) may merge whatever their
    facings: one sign seen from two streets, whose second street's rays the ray gate kept
    off its first landmark (in the fleet evaluation such pairs were 1.1-3.0 m apart; signs
    at a corner facing two streets stand 5-10 m apart)."""


@dataclass(frozen=True)
class Facing:
    """Facing estimates of ``k`` landmarks (struct of arrays; radians)."""

    azimuth: Array
    """Mean viewing azimuth (sign toward camera), clockwise from North, in [0, 2 pi)."""
    sigma: Array
    """Standard error of ``azimuth``."""
    spread: Array
    """Circular standard deviation of the rays' viewing azimuths."""
    known: NDArray[np.bool_]
    """Enough rays for a facing; where False the other fields are 0 and mean nothing."""
    second: Array | None = None
    """A second street's viewing azimuth (NaN: none; None: none for any), from a copy of
    the sign merged in from that street: the ray gate lets its rays pass too."""

    def __len__(self) -> int:
        return int(self.azimuth.size)

    def take(self, idx: ArrayLike) -> Facing:
        i = np.asarray(idx)
        second = None if self.second is None else self.second[i]
        return Facing(self.azimuth[i], self.sigma[i], self.spread[i], self.known[i], second)

    @staticmethod
    def unknown(k: int) -> Facing:
        """``k`` landmarks without a facing (every ray compatible)."""
        z = np.zeros(k)
        return Facing(z, z, z, np.zeros(k, bool))

    @staticmethod
    def concat(parts: list[Facing]) -> Facing:
        """The parts' landmarks in order."""
        second = None
        if any(p.second is not None for p in parts):
            second = np.concatenate(
                [np.full(len(p), np.nan) if p.second is None else p.second for p in parts]
            )
        return Facing(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("azimuth", "sigma", "spread")
            ),
            np.concatenate([p.known for p in parts]).astype(bool),
            second,
        )

    def rows(self) -> Array:
        """(k, 4): azimuth, sigma, spread and 1.0 where known (a landmark record's form)."""
        return np.column_stack([self.azimuth, self.sigma, self.spread, self.known.astype(float)])

    @staticmethod
    def from_rows(rows: ArrayLike) -> Facing:
        """The facings of :meth:`rows`."""
        f = np.asarray(rows, float).reshape(-1, 4)
        return Facing(f[:, 0], f[:, 1], f[:, 2], f[:, 3] > 0)


def view_vectors(direction: ArrayLike) -> Array:
    """(n, 2) horizontal unit vectors (East, North) of ray directions (camera toward sign);
    zero for a vertical ray (it says nothing about the facing)."""
    d = np.asarray(direction, float)[:, :2]
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return np.divide(d, n, out=np.zeros_like(d), where=n > 0)


def summed_views(ids: ArrayLike, direction: ArrayLike) -> tuple[Array, Array, Array]:
    """Rays grouped by the landmark each went to (``ids``): per distinct id, the index of
    its first ray, the sum of its rays' :func:`view_vectors` and their count.

    >>> first, view, n = summed_views([7, 3, 7], [[1.0, 0, 0], [0, 2.0, 0], [1.0, 0, 0]])
    >>> first.tolist(), view.tolist(), n.tolist()
    ([1, 0], [[0.0, 1.0], [2.0, 0.0]], [1, 2])
    """
    _uniq, first, inv = np.unique(np.asarray(ids), return_index=True, return_inverse=True)
    view = np.zeros((first.size, 2))
    np.add.at(view, inv, view_vectors(direction))
    return first, view, np.bincount(inv, minlength=first.size)


def viewing_azimuth(direction: ArrayLike) -> Array:
    """(n,) azimuth from the sign toward the camera (of ``-direction``), radians clockwise
    from North, in [0, 2 pi)."""
    d = np.asarray(direction, float)
    return np.arctan2(-d[:, 0], -d[:, 1]) % (2 * np.pi)


def facing_from_sums(view: ArrayLike, n_rays: ArrayLike, n_eff: ArrayLike, min_rays: int) -> Facing:
    """Facings from view sums ``view`` (k, 2) of ``n_rays`` rays, standard errors over
    ``n_eff`` independent looks (clipped to [1, n_rays]); known from ``min_rays`` rays."""
    v = np.asarray(view, float).reshape(-1, 2)
    n = np.asarray(n_rays, float).reshape(-1)
    g = np.clip(np.asarray(n_eff, float).reshape(-1), 1.0, np.maximum(n, 1.0))
    length = np.hypot(v[:, 0], v[:, 1])
    known = (n >= max(min_rays, 1)) & (length > 0)
    r = np.divide(length, n, out=np.zeros_like(n), where=n > 0)
    # E[R^2] = rho^2 + (1 - rho^2) / n for n independent angles: the unbiased rho^2
    rho2 = np.where(n > 1, (n * r**2 - 1.0) / np.maximum(n - 1.0, 1.0), r**2)
    spread = np.sqrt(-np.log(np.clip(rho2, 1e-24, 1.0)))
    az = np.arctan2(-v[:, 0], -v[:, 1]) % (2 * np.pi)
    zero = np.zeros_like(n)
    return Facing(
        np.where(known, az, zero),
        np.where(known, spread / np.sqrt(g), zero),
        np.where(known, spread, zero),
        known,
    )


def angle_between(a: ArrayLike, b: ArrayLike) -> Array:
    """|a - b| wrapped to [0, pi] (radians)."""
    d = (np.asarray(a, float) - np.asarray(b, float) + np.pi) % (2 * np.pi) - np.pi
    return np.abs(d)


def ray_compatible(theta: ArrayLike, facing: Facing, cfg: FacingConfig) -> NDArray[np.bool_]:
    """Per pair, whether a ray of viewing azimuth ``theta`` may be of a landmark of facing
    ``facing`` (same length): an unknown facing accepts every ray."""
    gate = np.radians(cfg.max_view_deg) + cfg.k_sigma * facing.sigma
    ok = ~facing.known | (angle_between(theta, facing.azimuth) <= gate)
    if facing.second is not None:
        with np.errstate(invalid="ignore"):
            ok |= angle_between(theta, facing.second) <= np.radians(cfg.max_view_deg)
    return ok


def facings_compatible(a: Facing, b: Facing, max_deg: float, k_sigma: float) -> NDArray[np.bool_]:
    """Per pair, whether landmarks of facings ``a`` and ``b`` may be one sign: known facings
    at most ``max_deg + k_sigma * sqrt(sigma_a^2 + sigma_b^2)`` apart (unknown: yes)."""
    gate = np.radians(max_deg) + k_sigma * np.hypot(a.sigma, b.sigma)
    far = angle_between(a.azimuth, b.azimuth) > gate
    return ~(a.known & b.known & far)


def to_wire(f: Facing) -> tuple[Array, Array]:
    """Published form: (azimuth deg in [0, 360), sigma deg); both 0 where unknown (a known
    facing's sigma is floored at 0.01 deg so that 0 always means unknown)."""
    deg = np.where(f.known, np.degrees(f.azimuth) % 360.0, 0.0)
    deg = np.where(deg >= 360.0, 0.0, deg)  # float rounding of an azimuth just below 2 pi
    sig = np.where(f.known, np.clip(np.degrees(f.sigma), 0.01, 180.0), 0.0)
    return deg, sig
