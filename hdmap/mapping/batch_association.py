"""Association of many units at once: each unit's offset hypotheses iterated in lockstep.

For one unit (a vehicle pass's rays in one tile, with its candidate landmarks) the method
is that of :mod:`hdmap.mapping.association`: every ray against every candidate of its class
under the wide origin covariance (the pass's unknown GNSS bias), the per-image and
per-track assignment, the pass's offset from that assignment and the assignment again
under it (``offset_iterations``, stopping at a fixed point); with tracks, also the offsets
that put the unit's longest track on each of its candidates (``offset_hypotheses``), each
iterated the same way, the best-scored kept if it beats the first by
``offset_hypothesis_margin``.

Here a batch of units goes through it together: the units' rays, candidates and
(ray, landmark) pairs are concatenated, each hypothesis of each unit is a *virtual unit*
(a copy of its unit's rays and candidates), and every step is one evaluation over all
virtual units still iterating: the statistic over their pairs (:func:`~hdmap.mapping.
association.pair_stat`), the assignment (:func:`~hdmap.mapping.association.assign_tracks`,
with image, track and candidate ids distinct per virtual unit), the offsets as sums over
each unit's rows (:func:`estimate_offsets`). The work of a step is numpy calls over the
whole batch rather than per unit.

Invariant: a unit's association does not depend on the other units of the batch. Its
pairs, images, tracks and candidate slots are its own, and every sum runs over its own rows
in their order, so a unit gets the same result, to the bit, alone (:func:`associate`) as in
any batch. That is what lets the matcher associate the units of a gating tick together
(:mod:`hdmap.mapping.tick`) and still give the same map however entries are batched.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from hdmap.geo.signs import DEFAULT_SIZE_REL_SIGMA
from hdmap.mapping.association import (
    Association,
    GateConfig,
    LocalRays,
    Pairs,
    assign_tracks,
    origin_cov,
    pair_stat,
)
from hdmap.mapping.facing import Facing, ray_compatible, viewing_azimuth

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class UnitInput:
    """One unit to associate: its rays and its candidate landmarks (positions and
    covariances in the rays' frame, classes and, if known, facings)."""

    rays: LocalRays
    x: Array
    cov: Array
    cls: IntArray
    facing: Facing | None = None
    scale: Array | None = None
    """Per candidate its panel scale (NaN: unknown; ``Landmark.scale``), or None."""


@dataclass(frozen=True)
class _Batch:
    """Units concatenated: rays (image and track renumbered densely, distinct per unit,
    track 0 = none), candidate slots and same-class, facing-compatible pairs."""

    rays: LocalRays
    unit: IntArray
    """Unit of each ray."""
    ray0: IntArray
    """(n + 1) first ray of each unit."""
    lm0: IntArray
    """(n + 1) first candidate slot of each unit."""
    x: Array
    pairs: Pairs
    li: IntArray
    """Candidate slot of each pair (``pairs.ri``: its ray)."""
    pu: IntArray
    """Unit of each pair."""
    track_unit: IntArray
    """Unit of each dense track id (index 0: none; the units' own, not their copies')."""
    n: int

    @property
    def ri(self) -> IntArray:
        return self.pairs.ri


def _dense(unit: IntArray, ids: IntArray) -> IntArray:
    """Ids renumbered 0.. by (unit, id), order kept within a unit."""
    key = (unit.astype(np.int64) << 32) | ids.astype(np.int64)
    return np.unique(key, return_inverse=True)[1].astype(np.int64)


def _class_pairs(kr: IntArray, kl: IntArray) -> tuple[IntArray, IntArray]:
    """All (ray, slot) with equal keys, by ray then slot (the order of
    ``np.nonzero(kr[:, None] == kl[None, :])``)."""
    order = np.argsort(kl, kind="stable")
    ks = kl[order]
    lo = np.searchsorted(ks, kr, "left")
    cnt = np.searchsorted(ks, kr, "right") - lo
    ri = np.repeat(np.arange(kr.size), cnt)
    start = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt)
    return ri, order[np.arange(ri.size) + start]


def _gather(units: list[UnitInput], cfg: GateConfig, panel_rel_sigma: float) -> _Batch:
    """The units as one batch (see :class:`_Batch`)."""
    nr = np.array([len(u.rays) for u in units], np.int64)
    nl = np.array([u.x.shape[0] for u in units], np.int64)
    ray0, lm0 = np.r_[0, np.cumsum(nr)], np.r_[0, np.cumsum(nl)]
    n = len(units)
    unit = np.repeat(np.arange(n), nr)
    lm_unit = np.repeat(np.arange(n), nl)
    rays = LocalRays.concat([replace(u.rays, track=u.rays.tracks) for u in units])
    track = rays.tracks
    on = track > 0
    dense_track = np.zeros(track.size, np.int64)
    dense_track[on] = _dense(unit[on], track[on]) + 1
    track_unit = np.zeros(int(dense_track.max(initial=0)) + 1, np.int64)
    track_unit[dense_track[on]] = unit[on]
    rays = replace(rays, image=_dense(unit, rays.image), track=dense_track)
    x = np.concatenate([np.asarray(u.x, float).reshape(-1, 3) for u in units])
    cov = np.concatenate([np.asarray(u.cov, float).reshape(-1, 3, 3) for u in units])
    cls = np.concatenate([u.cls for u in units]).astype(np.int64)
    kr = (unit << 20) | rays.sign_class
    ri, li = _class_pairs(kr, (lm_unit << 20) | cls)
    if any(u.facing is not None for u in units) and ri.size:
        facing = Facing.concat(
            [
                Facing.unknown(k) if u.facing is None else u.facing
                for u, k in zip(units, nl.tolist(), strict=True)
            ]
        )
        seen = ray_compatible(viewing_azimuth(rays.direction[ri]), facing.take(li), cfg.facing)
        ri, li = ri[seen], li[seen]
    pairs = Pairs.of(rays, ri, x[li], cov[li])
    if any(u.scale is not None for u in units):
        scale = np.concatenate(
            [
                np.full(k, np.nan) if u.scale is None else np.asarray(u.scale, float)
                for u, k in zip(units, nl.tolist(), strict=True)
            ]
        )
        pairs = replace(pairs, scale=scale[li], panel_rel_sigma=panel_rel_sigma)
    return _Batch(rays, unit, ray0, lm0, x, pairs, li, unit[ri], track_unit, n)


def _ranges(starts: IntArray, ends: IntArray) -> IntArray:
    """``np.arange(s, e)`` of every (s, e), concatenated."""
    n = ends - starts
    return np.repeat(starts - np.r_[0, np.cumsum(n)[:-1]], n) + np.arange(int(n.sum()))


def _with_copies(b: _Batch, base: IntArray) -> _Batch:
    """``b`` followed by a copy of each of its units ``base`` (units ``b.n``, ``b.n + 1``,
    ...): the same rays, candidates and pairs, with image and track ids of their own."""
    p0 = np.searchsorted(b.pu, np.arange(b.n + 1))  # each unit's pairs (by unit)
    nr, nl, npair = (z[base + 1] - z[base] for z in (b.ray0, b.lm0, p0))
    copy = np.arange(base.size)
    ray_copy, pair_copy = np.repeat(copy, nr), np.repeat(copy, npair)
    ray0 = b.ray0[-1] + np.r_[0, np.cumsum(nr)]
    lm0 = b.lm0[-1] + np.r_[0, np.cumsum(nl)]
    rr = _ranges(b.ray0[base], b.ray0[base + 1])
    pr = _ranges(p0[base], p0[base + 1])
    lr = _ranges(b.lm0[base], b.lm0[base + 1])
    c = b.rays.take(rr)
    img = (ray_copy + 1) * (int(b.rays.image.max(initial=0)) + 1)
    trk = (ray_copy + 1) * (int(b.rays.tracks.max(initial=0)) + 1)
    c = replace(c, image=c.image + img, track=np.where(c.tracks > 0, c.tracks + trk, 0))
    src = b.pairs
    ri = b.ri[pr] - b.ray0[base][pair_copy] + ray0[pair_copy]
    pairs = Pairs(
        np.r_[src.ri, ri],
        *(np.concatenate([f, f[pr]]) for f in (src.origin, src.direction, src.x, src.cov)),
        np.concatenate([src.measured, src.measured[pr]]),
        None if src.scale is None else np.concatenate([src.scale, src.scale[pr]]),
    )
    return _Batch(
        LocalRays.concat([b.rays, c]),
        np.r_[b.unit, b.n + ray_copy],
        np.r_[b.ray0, ray0[1:]],
        np.r_[b.lm0, lm0[1:]],
        np.concatenate([b.x, b.x[lr]]),
        pairs,
        np.r_[b.li, b.li[pr] - b.lm0[base][pair_copy] + lm0[pair_copy]],
        np.r_[b.pu, b.n + pair_copy],
        b.track_unit,
        b.n + base.size,
    )


def estimate_offsets(
    rays: LocalRays,
    unit: IntArray,
    n: int,
    x: Array,
    assigned: IntArray,
    active: BoolArray,
    bias_h: float,
    bias_v: float,
) -> tuple[Array, Array]:
    """The shared origin offset of each active unit (``unit``: each ray's, of ``n``) from
    its assigned rays (``assigned``: the row of ``x`` per ray, -1 none), and its covariance
    (the others: zero, the prior's): weighted least squares on perpendicular residuals with
    a zero-mean prior of the assumed bias size (so an unobservable direction stays at 0),
    summed per unit in row order."""
    prior = np.diag([1 / bias_h**2, 1 / bias_h**2, 1 / bias_v**2])
    m = (assigned >= 0) & active[unit]
    d, a = rays.direction[m], rays.origin[m]
    xl = x[assigned[m]]
    rng = np.linalg.norm(xl - a, axis=1)
    sig_ang = np.hypot(rays.sigma_az[m], rays.sigma_el[m]) / np.sqrt(2)
    w = 1.0 / ((rng * sig_ang) ** 2 + rays.sigma_pos_h[m] ** 2)
    p = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    u = unit[m]
    info = np.zeros((n, 3, 3))
    np.add.at(info, u, w[:, None, None] * p)
    rhs = np.zeros((n, 3))
    np.add.at(rhs, u, w[:, None] * (p @ (xl - a)[:, :, None])[:, :, 0])
    cov = np.linalg.inv(info + prior)
    return (cov @ rhs[:, :, None])[:, :, 0], cov


def estimate_offset(
    rays: LocalRays, assigned: IntArray, x: Array, bias_h: float, bias_v: float
) -> tuple[Array, Array]:
    """One unit's shared origin offset from its assigned rays, and its covariance
    (:func:`estimate_offsets` of one unit)."""
    o, c = estimate_offsets(
        rays, np.zeros(len(rays), np.int64), 1, x, assigned, np.ones(1, bool), bias_h, bias_v
    )
    return o[0], c[0]


@dataclass
class _Fits:
    """The current hypothesis of every virtual unit: per ray its slot (-1 none) and whether
    it is a track's unlinked ray, per pair the statistic, per unit the offset."""

    best: IntArray
    unlinked: BoolArray
    cost: Array
    offset: Array
    offset_cov: Array

    def update(self, b: _Batch, units: BoolArray, other: _Fits) -> None:
        """Take ``other``'s rows of ``units``."""
        rm, pm = units[b.unit], units[b.pu]
        self.best[rm] = other.best[rm]
        self.unlinked[rm] = other.unlinked[rm]
        self.cost[pm] = other.cost[pm]
        self.offset[units] = other.offset[units]
        self.offset_cov[units] = other.offset_cov[units]


def _assigned_at(b: _Batch, active: BoolArray, o: Array, oc: Array, cfg: GateConfig) -> _Fits:
    """The assignment of the active units with their origins moved by ``o`` (their
    covariance ``oc``); rows of the others are -1 / inf."""
    pm = active[b.pu]
    rows = None if pm.all() else np.flatnonzero(pm)  # None: every pair, in place
    sel = slice(None) if rows is None else rows
    narrow = origin_cov(b.rays, 0.0, 0.0) + oc[b.unit]
    cost = pair_stat(b.rays, b.pairs, narrow, cfg, o[b.pu[sel]], rows)[0]
    link_gate = cfg.chi2_gate * cfg.track_link_factor
    best, unlinked = assign_tracks(
        b.rays, b.ri[sel], b.li[sel], cost[sel], cfg.chi2_gate, link_gate
    )
    return _Fits(best, unlinked, cost, o.copy(), oc.copy())


def _refine(b: _Batch, fits: _Fits, active: BoolArray, cfg: GateConfig) -> None:
    """``cfg.offset_iterations`` times, for every active unit: the offset from its
    assignment, then the assignment under it (while at least ``min_offset_rays`` rays are
    assigned); a unit whose assignment comes back unchanged is at a fixed point and
    stops."""
    active = active.copy()
    for _ in range(cfg.offset_iterations):
        n_assigned = np.bincount(b.unit[fits.best >= 0], minlength=b.n)
        active &= n_assigned >= cfg.min_offset_rays
        if not active.any():
            return
        o, oc = estimate_offsets(
            b.rays,
            b.unit,
            b.n,
            b.x,
            fits.best,
            active,
            cfg.pass_bias_sigma_m,
            cfg.vertical_bias_sigma_m,
        )
        new = _assigned_at(b, active, o, oc, cfg)
        changed = np.zeros(b.n, bool)
        diff = (new.best != fits.best) & active[b.unit]
        changed[b.unit[diff]] = True
        fits.update(b, active, new)
        active &= changed


def _scores(b: _Batch, fits: _Fits, cfg: GateConfig) -> Array:
    """How well each virtual unit's hypothesis explains its unit: the summed margins
    ``chi2_gate - chi2`` of the pairs it links, minus the offset's chi-square under the
    pass-bias prior (both twice a log-likelihood ratio)."""
    linked = (fits.best[b.ri] == b.li) & np.isfinite(fits.cost)
    margin = np.bincount(b.pu[linked], cfg.chi2_gate - fits.cost[linked], minlength=b.n)
    prior = np.array([cfg.pass_bias_sigma_m, cfg.pass_bias_sigma_m, cfg.vertical_bias_sigma_m])
    return margin - np.sum((fits.offset / prior) ** 2, axis=1)


def _alternative_seeds(
    b: _Batch, wide_cost: Array, cfg: GateConfig
) -> tuple[IntArray, IntArray, IntArray]:
    """Per alternative hypothesis (by unit, most gated rays first): its unit, the candidate
    slot its unit's longest track is put on, and that track (dense id). The candidates are
    those the track's rays gate to under the wide origin covariance (the one the first fit
    gave it too: all its rays on it move the offset differently)."""
    none = np.zeros(0, np.int64)
    track = b.rays.track
    cand = np.flatnonzero(np.isfinite(wide_cost) & (track[b.ri] > 0))
    if cfg.offset_hypotheses <= 0 or cand.size == 0:
        return none, none, none
    ids, n_pairs = np.unique(track[b.ri[cand]], return_counts=True)
    tu = b.track_unit[ids]
    order = np.lexsort((ids, -n_pairs, tu))  # per unit: most pairs, then the lowest id
    first = np.r_[True, tu[order][1:] != tu[order][:-1]]
    longest = np.zeros(b.n, np.int64)
    longest[tu[order][first]] = ids[order][first]
    on = cand[track[b.ri[cand]] == longest[b.pu[cand]]]
    slots, n_rays = np.unique(b.li[on], return_counts=True)
    su = np.repeat(np.arange(b.n), np.diff(b.lm0))[slots]
    order = np.lexsort((slots, -n_rays, su))  # per unit: most rays, then the lowest slot
    su, slots = su[order], slots[order]
    rank = np.arange(su.size) - np.searchsorted(su, su, "left")
    keep = rank < cfg.offset_hypotheses
    return su[keep], slots[keep], longest[su[keep]]


def associate_units(
    units: list[UnitInput], cfg: GateConfig, panel_rel_sigma: float = DEFAULT_SIZE_REL_SIGMA
) -> list[Association]:
    """Associate each unit's rays with its candidate landmarks (see the module); a pair
    whose ray is seen from a direction its landmark's facing does not allow
    (:func:`hdmap.mapping.facing.ray_compatible`) is no candidate. ``panel_rel_sigma``:
    the catalogue's panel spread the rays' range sigmas include (taken out where a
    landmark's own panel scale is known: ``EstimatorConfig.panel_rel_sigma``)."""
    if not units:
        return []
    b = _gather(units, cfg, panel_rel_sigma)
    bias_h, bias_v = cfg.pass_bias_sigma_m, cfg.vertical_bias_sigma_m
    wide_cost = pair_stat(b.rays, b.pairs, origin_cov(b.rays, bias_h, bias_v), cfg, None)[0]
    link_gate = cfg.chi2_gate * cfg.track_link_factor
    best, unlinked = assign_tracks(b.rays, b.ri, b.li, wide_cost, cfg.chi2_gate, link_gate)
    alt_unit, alt_slot, alt_track = _alternative_seeds(b, wide_cost, cfg)
    v = _with_copies(b, alt_unit) if alt_unit.size else b
    n_alt = v.n - b.n
    prior_cov = np.diag([bias_h, bias_h, bias_v]) ** 2
    fits = _Fits(
        np.r_[best, np.full(len(v.rays) - best.size, -1, np.int64)],
        np.r_[unlinked, np.zeros(len(v.rays) - best.size, bool)],
        np.r_[wide_cost, np.full(v.li.size - wide_cost.size, np.inf)],
        np.zeros((v.n, 3)),
        np.repeat(prior_cov[None], v.n, axis=0),
    )
    if n_alt:
        alts = np.r_[np.zeros(b.n, bool), np.ones(n_alt, bool)]
        # the seed: every ray of the unit's longest track on the candidate
        own = v.unit >= b.n
        k = v.unit[own] - b.n
        base_ray = b.ray0[alt_unit[k]] + np.flatnonzero(own) - v.ray0[v.unit[own]]
        seed = np.full(len(v.rays), -1, np.int64)
        on_track = b.rays.track[base_ray] == alt_track[k]
        slot = alt_slot[k] - b.lm0[alt_unit[k]] + v.lm0[b.n + k]
        seed[np.flatnonzero(own)[on_track]] = slot[on_track]
        o, oc = estimate_offsets(v.rays, v.unit, v.n, v.x, seed, alts, bias_h, bias_v)
        fits.update(v, alts, _assigned_at(v, alts, o, oc, cfg))
    _refine(v, fits, np.ones(v.n, bool), cfg)
    chosen = np.arange(b.n)
    if n_alt:
        score = _scores(v, fits, cfg)
        top = score[: b.n] + cfg.offset_hypothesis_margin
        for j, u in enumerate(alt_unit.tolist()):
            if score[b.n + j] > top[u]:
                chosen[u], top[u] = b.n + j, score[b.n + j] + cfg.offset_hypothesis_margin
    chi2 = np.full(len(v.rays), np.inf)
    sel = fits.best[v.ri] == v.li
    chi2[v.ri[sel]] = fits.cost[sel]
    paired = np.bincount(b.pu, minlength=b.n) > 0
    out = []
    for u, c in enumerate(chosen.tolist()):
        n = len(units[u].rays)
        if not paired[u]:
            out.append(
                Association(
                    np.full(n, -1, np.int64), np.full(n, np.inf), np.zeros(3), np.zeros((3, 3))
                )
            )
            continue
        rows = slice(v.ray0[c], v.ray0[c + 1])
        lm = fits.best[rows]
        out.append(
            Association(
                np.where(lm >= 0, lm - v.lm0[c], -1),
                chi2[rows],
                fits.offset[c],
                fits.offset_cov[c],
                fits.unlinked[rows] if (units[u].rays.tracks > 0).any() else None,
            )
        )
    return out


def associate(
    rays: LocalRays,
    x: Array,
    cov: Array,
    cls: IntArray,
    cfg: GateConfig,
    facing: Facing | None = None,
) -> Association:
    """Associate one unit's rays with landmarks (positions ``x``, covariances, classes and,
    if given, facings): :func:`associate_units` of that unit alone."""
    return associate_units([UnitInput(rays, x, cov, cls, facing)], cfg)[0]
