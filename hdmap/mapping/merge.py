"""Merging landmarks that are one sign.

A touched landmark and another of its class whose estimates agree (chi-square of the
difference under both gating covariances, and at most ``merge_max_m`` apart), that are
seen from the same side (compatible facings, :mod:`hdmap.mapping.facing`) and were
seldom detected in one image together
(``merge_max_covis``), are one sign: the one with fewer rays (equal: the younger id) folds
its sums into the other's (:meth:`LandmarkSums.merge_rows`) and is retired with
``merged_into`` in the assoc output, so the solver does the same and the publisher
removes it.

Where the estimates do not agree, three rules find copies of one sign by other
evidence: co-passes (:func:`_copy_of`), never being in one image while facing one way
(:func:`_copy_apart`), and a second street's copy whose rays' box ranges put their panel
at the sign's landmark (:func:`ghost_partner`). Pitfall: the last one is the only merge
across facings farther apart than the panel's cone; it rests on the box ranges, so
vehicles that send none (``range_m = 0``) leave second-street copies as they are.
"""

from __future__ import annotations

import numpy as np

from hdmap.geo.tiles import frame_map
from hdmap.mapping import box_ranges
from hdmap.mapping.facing import Facing, angle_between, facings_compatible
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import refresh
from hdmap.mapping.matching import Matching, facings_of
from hdmap.mapping.quiet import merge_rows


def merge_touched(m: Matching, ids: list[int]) -> None:
    """Merge each of the landmarks ``ids`` (in order) with its partner, if it has one."""
    if not m.config.merge:
        return
    for lid in ids:
        lm = m.state.landmarks.get(lid)
        if lm is None:  # merged away a moment ago
            continue
        other = merge_partner(m, lm)
        if other is None:
            continue
        n = m.sums.n_obs([lm.row, other.row])
        keep, drop = (lm, other) if (-n[0], lm.id) < (-n[1], other.id) else (other, lm)
        merge(m, keep, drop)


def _due(m: Matching, lm: Landmark) -> bool:
    """Whether ``lm`` looks for a partner now: at every pass from ``merge_min_passes`` to
    ``merge_every_pass_until`` (at least twice ``merge_min_passes``), then at every third."""
    cfg = m.config
    g = int(m.sums.n_passes([lm.row])[0])
    every = max(2 * cfg.merge_min_passes, cfg.merge_every_pass_until)
    return not (g < cfg.merge_min_passes or (g > every and g % 3))


def _candidates(m: Matching, lm: Landmark) -> list[Landmark]:
    """Other landmarks of ``lm``'s class around its tile with enough passes to merge."""
    cfg = m.config
    cands = [c for c in m.state.near(m.area(lm.tile)) if c.cls == lm.cls and c.id != lm.id]
    if cands and cfg.merge_min_passes > 0:
        n = m.sums.n_passes([c.row for c in cands])
        cands = [c for c, k in zip(cands, n, strict=True) if k >= cfg.merge_min_passes]
    return cands


def merge_partner(m: Matching, lm: Landmark) -> Landmark | None:
    """The same-class landmark ``lm`` is one sign with (best chi-square), if any."""
    if not _due(m, lm):
        return None
    cands = _candidates(m, lm)
    if not cands:
        return None
    cfg = m.config
    # ENU differences: the frame's rotation of ECEF differences (no projection needed)
    d = (np.array([c.x for c in cands]) - lm.x) @ m.frames(lm.home).rotation.T
    c = lm.cov[None] + np.array([c.cov for c in cands])
    chi2 = np.einsum("ki,ki->k", d, np.linalg.solve(c, d[:, :, None])[:, :, 0])
    near = np.flatnonzero(
        (chi2 <= cfg.merge_chi2) & (np.hypot(d[:, 0], d[:, 1]) <= cfg.merge_max_m)
    )
    # Pitfall: sort only the gated ones. A far landmark with a loose estimate (a few passes
    # from a street seen head-on) can have the smallest chi-square of all while beyond
    # merge_max_m; stopping at it kept a GSDC sign as two confirmed landmarks 1.1 m apart
    # (chi-square 2.5) for its last 100 passes.
    for k in near[np.argsort(chi2[near], kind="stable")].tolist():
        o = cands[k]
        if _seen_together(m, lm, o) or not _same_side(m, lm, o):
            continue
        return o
    dist = np.hypot(d[:, 0], d[:, 1])
    return (
        _copy_of(m, lm, cands, dist)
        or _copy_apart(m, lm, cands, dist)
        or ghost_partner(m, lm, cands, dist)
    )


def _copy_of(m: Matching, lm: Landmark, cands: list[Landmark], dist: np.ndarray) -> Landmark | None:
    """The candidate ``lm`` is a copy of (or that is a copy of ``lm``), by co-passes and
    co-visibility rather than by the estimates (``MatchingConfig.merge_copy_units``): the
    one most units linked together with it."""
    cfg = m.config
    if cfg.merge_copy_units <= 0:
        return None
    near = np.flatnonzero(dist <= cfg.merge_copy_max_m)
    n = np.array([m.state.copass.get(lm.id, cands[k].id) for k in near.tolist()], np.int64)
    others = [cands[k] for k in near[n >= cfg.merge_copy_units].tolist()]
    if not others:
        return None
    n = n[n >= cfg.merge_copy_units]
    rows = np.array([lm.row] + [o.row for o in others], np.int64)
    passes, rays = m.sums.n_passes(rows), m.sums.n_obs(rows)
    ok = n >= cfg.merge_copy_share * np.minimum(passes[0], passes[1:])
    ok &= _one_way_never_together(m, lm, others, rays, cfg.merge_copy_max_covis)
    if not ok.any():
        return None
    m.tally("merged_copies", 1)
    return others[int(np.argmax(np.where(ok, n, -1)))]  # most co-passes (first on a tie)


def _copy_apart(
    m: Matching, lm: Landmark, cands: list[Landmark], dist: np.ndarray
) -> Landmark | None:
    """The candidate ``lm`` is a copy of seen from other passes
    (``MatchingConfig.merge_apart_max_m``): same way, never in one image; the nearest."""
    cfg = m.config
    if cfg.merge_apart_max_m <= 0:
        return None
    near = np.flatnonzero(dist <= cfg.merge_apart_max_m)
    if not near.size:
        return None
    others = [cands[k] for k in near.tolist()]
    rays = m.sums.n_obs(np.array([lm.row] + [o.row for o in others], np.int64))
    if rays[0] < cfg.merge_apart_min_rays:
        return None
    ok = rays[1:] >= cfg.merge_apart_min_rays
    ok &= _one_way_never_together(m, lm, others, rays, cfg.merge_apart_max_covis)
    if not ok.any():
        return None
    m.tally("merged_apart", 1)
    return others[int(np.argmin(np.where(ok, dist[near], np.inf)))]


def ghost_partner(
    m: Matching, lm: Landmark, cands: list[Landmark], dist: np.ndarray
) -> Landmark | None:
    """The candidate that ``lm`` is a second-street copy of, or that is one of ``lm``
    (``MatchingConfig.merge_ghost_max_m``): the one whose box ranges agree best."""
    cfg = m.config
    if cfg.merge_ghost_max_m <= 0:
        return None
    near = np.flatnonzero(dist <= cfg.merge_ghost_max_m)
    if not near.size:
        return None
    others = [cands[k] for k in near.tolist()]
    lms = [lm, *others]
    rows = np.array([o.row for o in lms], np.int64)
    passes, rays = m.sums.n_passes(rows), m.sums.n_obs(rows)
    if passes[0] < cfg.merge_ghost_min_passes:
        return None
    f = facings_of(m, lms)
    ok = (passes[1:] >= cfg.merge_ghost_min_passes) & _streets_apart(m, f)
    ok &= _rarely_together(m, lm, others, rays, cfg.merge_apart_max_covis)
    best, best_q = None, np.inf
    for j in np.flatnonzero(ok).tolist():
        o = others[j]
        for g, s, az in ((lm, o, f.azimuth[0]), (o, lm, f.azimuth[j + 1])):
            q = _ghost_mismatch(m, g, s, float(az))
            if q is not None and q < best_q:
                best, best_q = o, q
    if best is not None:
        m.tally("merged_ghosts", 1)
    return best


def _ghost_mismatch(m: Matching, g: Landmark, s: Landmark, azimuth: float) -> float | None:
    """``|log q|``, ``q`` the mean relative range of ``g``'s rays at ``s`` over that of
    ``s``'s own rays there, when ``s`` is on ``g``'s line of sight (``azimuth``: from ``g``
    toward its cameras), the ranges tell the two places apart and ``q`` is within
    ``merge_ghost_tol``; else None."""
    cfg = m.config
    frame = m.frames(g.home)
    xs, xg = frame.from_ecef(np.stack([s.x, g.x])).reshape(2, 3)
    d = xs - xg
    if abs(d[0] * np.cos(azimuth) - d[1] * np.sin(azimuth)) > cfg.merge_ghost_across_m:
        return None
    at = box_ranges.mean_relative_range(np.stack([g.ranges, g.ranges]), np.stack([xs, xg]))
    own = box_ranges.mean_relative_range(s.ranges, m.frames(s.home).from_ecef(s.x[None]))[0]
    if not (np.all(at > 0) and own > 0):  # NaN (no ranged rays) fails too
        return None
    q = abs(float(np.log(at[0] / own)))
    apart = abs(float(np.log(at[0] / at[1])))
    if q > cfg.merge_ghost_tol or apart < 2 * cfg.merge_ghost_tol:
        return None
    return q


def _one_way_never_together(
    m: Matching, lm: Landmark, others: list[Landmark], rays: np.ndarray, max_covis: float
) -> np.ndarray:
    """Which of ``others`` face the way ``lm`` does (both facings known, within
    ``merge_copy_max_deg``) and were detected in one image with it in at most
    ``max_covis`` of the smaller one's rays (``rays``: ``lm``'s, then the others')."""
    f = facings_of(m, [lm, *others])
    ok = f.known[0] & f.known[1:]
    ok &= angle_between(f.azimuth[0], f.azimuth[1:]) <= np.radians(m.config.merge_copy_max_deg)
    return ok & _rarely_together(m, lm, others, rays, max_covis)


def _rarely_together(
    m: Matching, lm: Landmark, others: list[Landmark], rays: np.ndarray, max_covis: float
) -> np.ndarray:
    """Which of ``others`` were detected in one image with ``lm`` in at most ``max_covis``
    of the smaller one's rays (``rays``: ``lm``'s, then the others')."""
    covis = np.array([m.state.covis_count(lm.id, o.id) for o in others])
    return covis <= max_covis * np.maximum(np.minimum(rays[0], rays[1:]), 1)


def _streets_apart(m: Matching, f: Facing) -> np.ndarray:
    """Whether the first landmark of facings ``f`` and each other one are seen from two
    streets: both facings known, ``merge_ghost_min_deg`` or more apart."""
    far = angle_between(f.azimuth[0], f.azimuth[1:]) >= np.radians(m.config.merge_ghost_min_deg)
    return f.known[0] & f.known[1:] & far


def _seen_together(m: Matching, a: Landmark, b: Landmark) -> bool:
    """Whether ``a`` and ``b`` were detected in one image too often to be one sign."""
    n = m.sums.n_obs([a.row, b.row])
    return m.state.covis_count(a.id, b.id) > m.config.merge_max_covis * max(n.min(), 1)


def _same_side(m: Matching, a: Landmark, b: Landmark) -> bool:
    """Whether ``a`` and ``b`` are seen from the same side: their facings within
    ``acos(merge_min_view_cos)`` (60 degrees) plus ``k_sigma`` standard errors of the
    difference (:func:`hdmap.mapping.facing.facings_compatible`; a landmark with too few
    rays for a facing counts as the same side); closer than ``FacingConfig.same_place_m``,
    within ``2 max_view_deg`` (one sign seen from two streets, not two panels back to
    back)."""
    cfg = m.config.gate.facing
    f = facings_of(m, [a, b])
    fa, fb = f.take([0]), f.take([1])
    d = (b.x - a.x) @ m.frames(a.home).rotation.T  # ENU difference
    if float(np.hypot(d[0], d[1])) < cfg.same_place_m:
        # one place: one sign seen from two streets, unless seen from farther apart than
        # one panel's cone allows (2 V: two panels back to back)
        return bool(facings_compatible(fa, fb, 2 * cfg.max_view_deg, cfg.k_sigma)[0])
    max_deg = float(np.degrees(np.arccos(np.clip(m.config.merge_min_view_cos, -1.0, 1.0))))
    return bool(facings_compatible(fa, fb, max_deg, cfg.k_sigma)[0])


def merge(m: Matching, keep: Landmark, drop: Landmark) -> None:
    """``drop`` is ``keep``: its sums fold into ``keep``'s, its record goes, the home
    tile's output retires it into ``keep``, and ``keep``'s estimate is re-solved."""
    if m.config.merge_second_facing:
        f = facings_of(m, [keep, drop])
        if _streets_apart(m, f)[0]:  # its street's rays pass keep's gate from now on
            keep.second_facing = float(f.azimuth[1])
    rot, t = frame_map(m.frames(drop.home), m.frames(keep.home))
    merge_rows(m.quiet, m.sums, keep, drop, rot, t)
    drop.ranges = box_ranges.in_frame(drop.ranges, rot, t)[0]
    m.state.merge(keep, drop)
    m.out[drop.home].retired.append((drop.id, keep.id))
    m.tally("merged", 1)
    refresh(m, [keep.id])
