"""Merging landmarks that are one sign.

A touched landmark and another of its class whose estimates agree (chi-square of the
difference under both gating covariances, and at most ``merge_max_m`` apart), that are
seen from the same side and were seldom detected in one image together
(``merge_max_covis``), are one sign: the one with fewer rays (equal: the younger id) folds
its sums into the other's (:meth:`LandmarkSums.merge_rows`) and is retired with
``merged_into`` in the assoc output, so the solver does the same and the publisher
removes it.
"""

from __future__ import annotations

import numpy as np

from hdmap.geo.tiles import frame_map
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import refresh
from hdmap.mapping.matching import Matching
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
    twice that, then at every third."""
    cfg = m.config
    g = int(m.sums.n_passes([lm.row])[0])
    return not (g < cfg.merge_min_passes or (g > 2 * cfg.merge_min_passes and g % 3))


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
    near = (chi2 <= cfg.merge_chi2) & (np.hypot(d[:, 0], d[:, 1]) <= cfg.merge_max_m)
    for k in np.argsort(chi2, kind="stable").tolist():
        if not near[k]:
            break
        o = cands[k]
        if _seen_together(m, lm, o) or not _same_side(m, lm, o):
            continue
        return o
    return None


def _seen_together(m: Matching, a: Landmark, b: Landmark) -> bool:
    """Whether ``a`` and ``b`` were detected in one image too often to be one sign."""
    n = m.sums.n_obs([a.row, b.row])
    return m.state.covis_count(a.id, b.id) > m.config.merge_max_covis * max(n.min(), 1)


def _same_side(m: Matching, a: Landmark, b: Landmark) -> bool:
    """Whether ``a`` and ``b`` are seen from the same side (mean viewing directions within
    ``merge_min_view_cos``; no direction yet counts as the same side)."""
    va, vb = a.view, b.view
    norm = float(np.linalg.norm(va) * np.linalg.norm(vb))
    return not (norm > 0 and float(va @ vb) < m.config.merge_min_view_cos * norm)


def merge(m: Matching, keep: Landmark, drop: Landmark) -> None:
    """``drop`` is ``keep``: its sums fold into ``keep``'s, its record goes, the home
    tile's output retires it into ``keep``, and ``keep``'s estimate is re-solved."""
    rot, t = frame_map(m.frames(drop.home), m.frames(keep.home))
    merge_rows(m.quiet, m.sums, keep, drop, rot, t)
    m.state.merge(keep, drop)
    m.out[drop.home].retired.append((drop.id, keep.id))
    m.tally("merged", 1)
    refresh(m, [keep.id])
