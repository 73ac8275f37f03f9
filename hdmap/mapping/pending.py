"""Landmarks from the pending pool: rays no landmark took wait per tile; a pass's waiting
rays may start candidate landmarks (:func:`initiate`, with
:func:`hdmap.mapping.initiation.propose`), new landmarks are offered the waiting rays of
other passes (:func:`adopt`), and rays that waited too long go (:func:`expire`).
"""

from __future__ import annotations

import numpy as np

from hdmap.geo.tiles import in_region, quadkeys_of
from hdmap.mapping.association import associate, origin_cov, pair_chi2
from hdmap.mapping.initiation import propose
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import create, link, to_local
from hdmap.mapping.matching import Matching
from schemas.ids import pass_key


def initiate(
    m: Matching, tile: str, area: list[str], vehicle: str, pass_id: int, classes: np.ndarray
) -> set[int]:
    """Candidate landmarks from this pass's pending rays around ``tile``, for the classes
    that just got new pending rays (for the others, this pass's pending rays only
    shrank since they last failed to make a landmark). Returns the new landmarks' ids."""
    if classes.size == 0:
        return set()
    frame = m.frames(tile)
    key = pass_key(vehicle, pass_id)
    where: list[tuple[str, np.ndarray]] = []  # (tile, rows of its pending pool)
    for t in area:
        p = m.state.pending.get(t)
        if p is not None and (mine := np.flatnonzero(p.key == key)).size:
            where.append((t, mine))
    if not where:
        return set()
    parts = [m.state.pending[t].obs.take(i) for t, i in where]
    obs = type(parts[0]).concat(parts)
    received = max(float(m.state.pending[t].received_at[i].max()) for t, i in where)
    rays = to_local(frame, obs)
    created: set[int] = set()
    used = np.zeros(len(rays), bool)
    for cls in np.intersect1d(np.unique(rays.sign_class), classes):
        idx = np.flatnonzero(rays.sign_class == cls)
        for cand in propose(rays.take(idx), m.config.gate, m.config.init):
            members = idx[cand.members]
            lat, lon, h = frame.to_geodetic(cand.x[None])
            home_tile = str(quadkeys_of(lat, lon, m.zoom)[0])
            if not in_region(home_tile, m.region):
                home_tile = tile
            lm = create(m, home_tile, int(cls), frame.to_ecef(cand.x[None])[0], cand.cov)
            out = m.out[lm.home]
            out.created.append((lm.id, int(cls), float(lat[0]), float(lon[0]), float(h[0])))
            link(m, obs.take(members), [lm] * len(members), vehicle, pass_id, received)
            used[members] = True
            created.add(lm.id)
    drop_used(m, where, used)
    if created:
        m.tally("created", len(created))
        adopt(m, area, [m.state.landmarks[i] for i in sorted(created)])
    return created


def adopt(m: Matching, area: list[str], new: list[Landmark]) -> None:
    """Offer pending rays of other passes to freshly created landmarks."""
    for t in area:
        p = m.state.pending.get(t)
        if p is None or not len(p):
            continue
        frame = m.frames(t)
        x = frame.from_ecef(np.array([c.x for c in new]))
        cov = np.array([c.cov for c in new])
        cls = np.array([c.cls for c in new], np.int64)
        # only rays of the new landmarks' classes can match (associate pairs same-class
        # only): select them first, convert them once
        cand = np.flatnonzero(np.isin(p.obs.sign_class, cls))
        if cand.size == 0:
            continue
        local = to_local(frame, p.obs.take(cand))
        # a unit none of whose rays passes the wide gate (the first step of associate)
        # cannot be associated: offer only the others (exact, and the pool can be large)
        g = m.config.gate
        ri, li = np.nonzero(local.sign_class[:, None] == cls[None, :])
        wide = origin_cov(local, g.pass_bias_sigma_m, g.vertical_bias_sigma_m)
        chi2, ok = pair_chi2(local, ri, x[li], cov[li], wide, g)
        live = np.zeros(len(local), bool)
        live[ri[ok & (chi2 <= g.chi2_gate)]] = True
        if not live.any():
            continue
        # one unit per (vehicle, pass), in (vehicle, pass) order
        _u, first, inv = np.unique(p.key[cand], return_index=True, return_inverse=True)
        members = np.split(np.argsort(inv, kind="stable"), np.cumsum(np.bincount(inv))[:-1])
        units = sorted(
            (p.vehicle[cand[f]], int(p.pass_id[cand[f]]), js)
            for f, js in zip(first.tolist(), members, strict=True)
        )
        take = np.zeros(len(p), bool)
        links: list[tuple[np.ndarray, np.ndarray, str, int, float]] = []
        for v, pid, js in units:
            if not live[js].any():
                continue
            sel = cand[js]
            res = associate(local.take(js), x, cov, cls, m.config.gate)
            hit = res.landmark >= 0
            if hit.any():
                take[sel[hit]] = True
                rec = float(p.received_at[sel[hit]].max())
                links.append((sel[hit], res.landmark[hit], v, pid, rec))
        for sel, lmi, v, pid, rec in links:
            link(m, p.obs.take(sel), [new[k] for k in lmi], v, pid, rec)
            m.tally("adopted", len(sel))
        m.state.drop_pending(t, take)


def drop_used(m: Matching, where: list[tuple[str, np.ndarray]], used: np.ndarray) -> None:
    """Remove from each tile's pool the rows ``used`` marks (``used`` follows ``where``)."""
    start = 0
    for t, rows in where:
        u = used[start : start + rows.size]
        start += rows.size
        if u.any():
            mask = np.zeros(len(m.state.pending[t]), bool)
            mask[rows[u]] = True
            m.state.drop_pending(t, mask)


def expire(m: Matching) -> int:
    """Drop pending rays added more than ``pending_ttl_s`` ago; returns how many."""
    cutoff = m.clock() - m.config.pending_ttl_s
    n = 0
    for t, p in list(m.state.pending.items()):
        old = p.added_at < cutoff
        if old.any():
            m.state.drop_pending(t, old)
            n += int(old.sum())
    return n
