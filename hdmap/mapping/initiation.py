"""Landmark initiation: consistent rays of one pass become a candidate landmark.

The map starts empty. Rays that match no landmark wait in the matcher's pending
pool. Rays of one pass share that pass's GNSS bias, so they intersect
consistently with each other even when the bias is metres: candidates are formed
within a pass (same vehicle, same pass, same class), from distinct images and
viewpoints. The candidate's position is then biased by that pass's offset; later
passes refine it (and their own offsets are estimated against it).

Triangulation combines the orthogonal-distance (bearing) terms with the size-based
range of each ray as a pseudo-measurement along the ray, so a sign seen almost
straight ahead (little parallax) still gets a position:

    A = sum w_j P_j + sum v_j d_j d_j^T,   b = sum w_j P_j a_j + sum v_j d_j (d_j^T a_j + r_j)

with w_j = 1 / (r_j^2 s_j^2 + s_pos^2) and v_j = 1 / s_r,j^2 (0 without a range).

>>> import numpy as np
>>> d = np.array([[1.0, 0, 0], [0, 1.0, 0]])
>>> a = np.array([[-10.0, 0, 0], [0, -10.0, 0]])
>>> r = LocalRays(a, d, *np.full((2, 2), 0.01), *np.full((2, 2), 1.0), np.zeros(2),
...               np.zeros(2), np.array([0, 1]), np.array([4, 4]))
>>> triangulate(r)[0].round(6).tolist()
[0.0, 0.0, 0.0]
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from hdmap.mapping.association import (
    GateConfig,
    LocalRays,
    Pairs,
    origin_cov,
    pair_stat,
    track_spans,
)

Array = NDArray[np.float64]

DEFAULT_RANGE_M = 30.0


@dataclass(frozen=True)
class InitConfig:
    min_rays: int = 4
    min_images: int = 4
    min_parallax_rad: float = 0.035
    """Spread of bearings a candidate needs unless >= 2 of its rays carry a range."""
    min_ranged: int = 2
    max_cond: float = 1e8
    by_track: bool = True
    """A candidate never joins rays of two tracks in view together (two signs): its rays
    come from the seed's track and tracks that do not overlap it in images (the same sign
    after a broken track, or another one the gate tells apart); untracked rays from the
    untracked ones."""


@dataclass(frozen=True)
class Candidate:
    x: Array
    cov: Array
    members: NDArray[np.int64]
    """Indices into the rays passed to :func:`propose`."""


MIN_SIGMA_ANGLE_RAD = 1e-9
MIN_SIGMA_POS_M = 1e-6
MIN_SIGMA_RANGE_M = 1e-6
"""Floors on the sigmas used as weights: a valid but tiny reported sigma (1e-300) must
not make one ray's weight infinite."""


def triangulate(rays: LocalRays, ranges: bool = True) -> tuple[Array, Array]:
    """Least-squares point of rays (bearing terms + range pseudo-measurements) and its cov
    (NaN where the rays fix no point)."""
    x, cov = triangulate_groups(rays, np.zeros(len(rays), np.int64), 1, ranges)
    return x[0], cov[0]


def normal_terms(rays: LocalRays, ranges: bool = True) -> tuple[Array, Array]:
    """Each ray's terms of the triangulation's normal equations: (n, 3, 3) and (n, 3)
    (module docstring: ``w_j P_j + v_j d_j d_j^T`` and the matching right-hand side)."""
    d, a = rays.direction, rays.origin
    r_hat = np.where(rays.range_m > 0, rays.range_m, DEFAULT_RANGE_M)
    s_ang2 = np.maximum((rays.sigma_az**2 + rays.sigma_el**2) / 2.0, MIN_SIGMA_ANGLE_RAD**2)
    w = 1.0 / (r_hat**2 * s_ang2 + np.maximum(rays.sigma_pos_h, MIN_SIGMA_POS_M) ** 2)
    dd = d[:, :, None] * d[:, None, :]
    wp = w[:, None, None] * (np.eye(3)[None] - dd)
    terms_a, terms_b = wp.copy(), np.einsum("nij,nj->ni", wp, a)
    if ranges:
        has = (rays.range_m > 0) & (rays.sigma_range_m > 0)
        s_r = np.maximum(np.where(has, rays.sigma_range_m, 1.0), MIN_SIGMA_RANGE_M)
        v = np.where(has, 1.0 / s_r**2, 0.0)
        terms_a += v[:, None, None] * dd
        terms_b += (v * (np.einsum("ki,ki->k", d, a) + rays.range_m))[:, None] * d
    return terms_a, terms_b


def triangulate_groups(
    rays: LocalRays, groups: NDArray[np.int64], k: int, ranges: bool = True
) -> tuple[Array, Array]:
    """:func:`triangulate` of the rays of each group ``0..k-1`` at once: points (k, 3) and
    covariances (k, 3, 3), NaN where a group fixes no point (or has no rays)."""
    return _solve_groups(*normal_terms(rays, ranges), np.asarray(groups, np.int64), k)


def _solve_terms(terms_a: Array, terms_b: Array) -> tuple[Array, Array]:
    """The point and covariance of one group's normal-equation terms."""
    x, cov = _solve_groups(terms_a, terms_b, np.zeros(terms_a.shape[0], np.int64), 1)
    return x[0], cov[0]


def _solve_groups(
    terms_a: Array, terms_b: Array, g: NDArray[np.int64], k: int
) -> tuple[Array, Array]:
    """Points and covariances of the groups ``g`` of rays with these terms (summed in row
    order)."""
    big_a = np.zeros((k, 3, 3))
    b = np.zeros((k, 3))
    np.add.at(big_a, g, terms_a)
    np.add.at(b, g, terms_b)
    good = np.isfinite(big_a).all(axis=(1, 2)) & np.isfinite(b).all(axis=1)
    good &= np.bincount(g, minlength=k)[:k] > 0
    cov = np.full((k, 3, 3), np.nan)
    if good.any():
        cov[good] = np.linalg.pinv(big_a[good])
    x = np.einsum("kij,kj->ki", cov, b)
    return x, cov


def ray_point(rays: LocalRays, j: int) -> tuple[Array, Array]:
    """One ray's point: at its range (the default range without one), with its angular and
    origin sigma across the ray and its range sigma (the range itself without one) along.

    >>> r = LocalRays(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]), *np.full((4, 1), 0.01),
    ...               np.array([20.0]), np.array([2.0]), np.zeros(1), np.ones(1))
    >>> x, cov = ray_point(r, 0)
    >>> x.tolist(), np.sqrt(np.diag(cov)).round(2).tolist()
    ([0.0, 20.0, 0.0], [0.21, 2.0, 0.21])
    """
    ranged = rays.range_m[j] > 0
    r = rays.range_m[j] if ranged else DEFAULT_RANGE_M
    d = rays.direction[j]
    s_along = rays.sigma_range_m[j] if ranged else r
    s_across = r * max(rays.sigma_az[j], rays.sigma_el[j]) + rays.sigma_pos_h[j]
    cov = s_across**2 * (np.eye(3) - np.outer(d, d)) + s_along**2 * np.outer(d, d)
    return rays.origin[j] + r * d, cov


def bearing_spread(rays: LocalRays, x: Array) -> float:
    """Largest angle (rad) between directions from x back to the ray origins."""
    v = rays.origin - x
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    c = np.clip(v @ v.T, -1.0, 1.0)
    return float(np.arccos(c.min()))


def _best_per_image(idx: NDArray[np.int64], chi2: Array, images: NDArray) -> NDArray[np.int64]:
    """Of the rays ``idx``, the one with the smallest ``chi2`` per image.

    >>> _best_per_image(np.array([], np.int64), np.array([]), np.array([0, 1])).tolist()
    []
    >>> idx, chi2, img = np.array([0, 1, 2]), np.array([3.0, 1.0, 2.0]), np.array([7, 7, 8])
    >>> _best_per_image(idx, chi2, img).tolist()
    [1, 2]
    """
    if idx.size == 0:
        return idx
    order = np.lexsort((chi2, images[idx]))
    idx, img = idx[order], images[idx][order]
    first = np.r_[True, img[1:] != img[:-1]]
    return np.sort(idx[first])


def seeds_of(rays: LocalRays, may_seed: NDArray[np.bool_] | None = None) -> NDArray[np.int64]:
    """The rays :func:`propose` grows candidates from, in order: of those ``may_seed``
    marks (None: all), the ones with a range, or all of them if none has one.

    >>> r = LocalRays(*np.zeros((2, 3, 3)), *np.ones((4, 3)), np.array([0.0, 20.0, 0.0]),
    ...               np.ones(3), np.arange(3), np.zeros(3, np.int64))
    >>> seeds_of(r).tolist(), seeds_of(r, np.array([True, False, True])).tolist()
    ([1], [0, 2])
    """
    pick = np.ones(len(rays), bool) if may_seed is None else np.asarray(may_seed, bool)
    ranged = np.flatnonzero(pick & (rays.range_m > 0))
    return ranged if ranged.size else np.flatnonzero(pick)


def propose(
    rays: LocalRays,
    gate: GateConfig,
    cfg: InitConfig,
    seeds: NDArray[np.int64] | None = None,
) -> list[Candidate]:
    """Candidates from the rays of ONE pass and ONE class (greedy, deterministic); with
    tracks, never from two tracks in view together (``InitConfig.by_track``). Candidates
    grow from ``seeds`` (indices into ``rays``; None: :func:`seeds_of` all of them), each
    over all of ``rays`` not taken yet: the work is ``len(seeds)`` times ``len(rays)``."""
    n = len(rays)
    if seeds is None:
        seeds = seeds_of(rays)
    if n < cfg.min_rays or seeds.size == 0:
        return []
    used = np.zeros(n, bool)
    track = rays.tracks
    u, inv = np.unique(track, return_inverse=True)
    span = track_spans(track, rays.image, u)[inv]
    first = np.where(track > 0, span[:, 0], rays.image)
    last = np.where(track > 0, span[:, 1], rays.image)
    white = origin_cov(rays, 0.0, 0.0)
    # per ray, once: the triangulation's terms and the pairs' ray side (each iteration
    # below sums the members' terms and gates the free rays against one point: the same
    # arithmetic as triangulate / pair_chi2 on them, to the bit)
    terms = normal_terms(rays)
    ray_side = Pairs.of(rays, np.arange(n), np.zeros((n, 3)), np.zeros((n, 3, 3)))
    out: list[Candidate] = []
    need = max(cfg.min_rays, cfg.min_images)
    for s in seeds:
        if used[s]:
            continue
        x, cov = ray_point(rays, int(s))
        members = np.array([], np.int64)
        pool = ~used
        if cfg.by_track:
            apart = (first > last[s]) | (last < first[s])
            pool &= (track == track[s]) | ((track > 0) & (track[s] > 0) & apart)
        if np.unique(rays.image[pool]).size < need:
            continue  # members are one ray per image of the pool: too few images to pass
        free = np.flatnonzero(pool)
        for _ in range(3):
            at = replace(
                ray_side, x=np.broadcast_to(x, (n, 3)), cov=np.broadcast_to(cov, (n, 3, 3))
            )
            chi2, ok = pair_stat(rays, at, white, gate, None, free)
            chi2, ok = chi2[free], ok[free]
            hit = ok & (chi2 <= gate.chi2_gate)
            before, members = members, _best_per_image(free[hit], chi2[hit], rays.image)
            if members.size < 2:
                break
            if np.array_equal(members, before):
                break  # a fixed point: the same members solve to the same x and cov
            x, cov = _solve_terms(terms[0][members], terms[1][members])
            if not np.isfinite(cov).all():
                break
        if members.size < cfg.min_rays or np.unique(rays.image[members]).size < cfg.min_images:
            continue
        sub = rays.take(members)
        ranged = int(((sub.range_m > 0) & (sub.sigma_range_m > 0)).sum())
        if bearing_spread(sub, x) < cfg.min_parallax_rad and ranged < cfg.min_ranged:
            continue
        if not (np.isfinite(x).all() and np.isfinite(cov).all()):
            continue
        if np.linalg.cond(np.linalg.pinv(cov)) > cfg.max_cond:
            continue
        used[members] = True
        out.append(Candidate(x, cov, members))
    return out
