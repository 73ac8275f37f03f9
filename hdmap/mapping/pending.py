"""Landmarks from the pending pool: rays no landmark took wait per tile; a pass's waiting
rays may start candidate landmarks (:func:`initiate`, with
:func:`hdmap.mapping.initiation.propose`; at the end of their gating tick,
:func:`initiate_waiting`), new landmarks are offered the waiting rays of other passes
(:func:`adopt`), and rays that waited too long go (:func:`expire`).

Budgets (``MatchingConfig.pending_max_per_pass``, ``pending_max_per_vehicle``,
``quarantine_after``; :func:`enforce_budget`): what one upload costs here is bounded by
the upload's size and the budgets, not by what a pass or a vehicle accumulated. A pass
over its budget loses its oldest waiting rays; one that then keeps making nothing is
quarantined (no more initiation attempts; its rays still link and may be adopted).
"""

from __future__ import annotations

import numpy as np

from hdmap.geo.tiles import in_region, quadkeys_of
from hdmap.mapping.association import LocalRays, origin_cov, pair_chi2
from hdmap.mapping.batch_association import UnitInput, associate_units
from hdmap.mapping.initiation import propose, seeds_of
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import create, link, local_rays, to_local
from hdmap.mapping.matching import Matching
from hdmap.mapping.pool import PendingTile
from schemas.ids import pass_key

NO_LANDMARK = "no_landmark_at_budget"
"""Quarantine reason: the pass filled its pending budget and then made no landmark in
``quarantine_after`` initiation attempts in a row."""


def _oldest(p: PendingTile, rows: np.ndarray, n: int) -> np.ndarray:
    """The ``n`` oldest of ``rows`` (by the time they were pooled; rows are in pool order)."""
    return rows[np.argsort(p.added_at[rows], kind="stable")[:n]]


def enforce_budget(m: Matching, tile: str, vehicle: str, pass_id: int, touch: bool = True) -> int:
    """After a unit of (``vehicle``, ``pass_id``) pooled its rays in ``tile`` and had its
    initiation attempt (:func:`initiate`): evict the oldest waiting rays of the pass over
    ``pending_max_per_pass`` and of the vehicle over ``pending_max_per_vehicle`` from the
    tile's pool (counted ``pending_evicted``, and by budget ``pending_evicted.pass``,
    ``pending_evicted.vehicle``). A pass that loses rays
    gets a budget record (:class:`~hdmap.mapping.landmarks.PassBudget`), which its later
    uploads keep alive (``touch``: this is one of them). Returns the rays evicted."""
    cfg = m.config
    key = pass_key(vehicle, pass_id)
    p = m.state.pending.get(tile)
    drop = np.zeros(0 if p is None else len(p), bool)
    if p is not None and cfg.pending_max_per_pass > 0:
        over = p.count_of(key) - cfg.pending_max_per_pass
        if over > 0:
            drop[_oldest(p, np.flatnonzero(p.key == key), over)] = True
            m.tally("pending_evicted.pass", over)
            m.state.budget_of(vehicle, pass_id).evicted += over
    if p is not None and cfg.pending_max_per_vehicle > 0:
        over = p.per_vehicle[vehicle] - int(drop.sum()) - cfg.pending_max_per_vehicle
        if over > 0:  # found by name only when over (the count is kept as rays come and go)
            theirs = np.flatnonzero((p.vehicle == vehicle) & ~drop)
            drop[_oldest(p, theirs, over)] = True
            m.tally("pending_evicted.vehicle", over)
    n = int(drop.sum())
    if n:
        m.state.drop_pending(tile, drop)
        m.tally("pending_evicted", n)
    if touch:
        touch_budget(m, vehicle, pass_id)
    return n


def touch_budget(m: Matching, vehicle: str, pass_id: int) -> None:
    """An upload of the pass keeps its budget record (if it has one) alive."""
    if pass_key(vehicle, pass_id) in m.state.passes:
        m.state.budget_of(vehicle, pass_id).last_at = m.now


def initiate(
    m: Matching,
    tile: str,
    area: list[str],
    vehicle: str,
    pass_id: int,
    classes: np.ndarray | None = None,
) -> set[int]:
    """Candidate landmarks from this pass's pending rays around ``tile``, for the classes
    that just got new pending rays (for the others, this pass's pending rays only
    shrank since they last failed to make a landmark; None: the classes of its rays there
    not tried yet). Returns the new landmarks' ids.

    Seeds (``MatchingConfig.init_reseed_max``): above that many waiting rays of a class,
    candidates grow only from the rays not tried as seeds yet, over all of the pass's
    waiting rays (at most that many: every one seeds again). Every ray is tried in the unit
    that pools it or at its tick's end (its class is among ``classes``), so these are the
    rays pooled since, and the work is (those rays) x (the pass's: at most 9 tiles' budgets
    and what it pooled in the tick, :func:`enforce_budget` runs after this; a pass over its
    budget ends its tick at its upload, :func:`over_budget`). Invariant:
    every tried ray of the pool has been a seed against the pool as it was then, and made
    nothing. Since then the pass's pool changed only by (a) rays added: a candidate that
    needs one of them contains one, and growing from any member of a cluster finds the
    cluster (up to the greedy's order, which decides which seed's position the first gate
    starts from); (b) rays taken out (by candidates, adoption, expiry, eviction): fewer
    rays give a cluster no more members, images or spread, so a seed that failed does not
    pass now (not a theorem: the re-triangulation moves with the rays; what it can miss
    waits for adoption like any pending ray). So seeding from new rays finds what a full
    re-run finds, without the re-run's O(P^2) per upload in the pass's pending rays P.

    Counted: ``init_rays`` (rays handed to :func:`~hdmap.mapping.initiation.propose`),
    ``init_seeds`` (seeds it grew from), ``init_too_few`` (attempts with too few rays of
    every untried class: nothing gathered), ``init_new_seeds_only`` (classes seeded from the
    new rays only), ``init_skipped_quarantined`` (attempts a
    quarantined pass did not get), ``passes_quarantined`` (and by reason)."""
    if classes is not None and classes.size == 0:
        return set()
    key = pass_key(vehicle, pass_id)
    where: list[tuple[str, np.ndarray]] = []  # (tile, rows of its pending pool)
    for t in area:
        p = m.state.pending.get(t)
        if p is not None and p.count_of(key):
            where.append((t, np.flatnonzero(p.key == key)))
    budget = m.state.passes.get(key)
    if quarantined(m, vehicle, pass_id):
        m.tally("init_skipped_quarantined", 1)
        for t, i in where:
            m.state.mark_tried(t, i)  # no attempt is due for them at the tick's end
        return set()
    if not where:
        return set()
    frame = m.frames(tile)
    pools = [(m.state.pending[t], i) for t, i in where]
    sign_class = np.concatenate([p.obs.sign_class[i] for p, i in pools]).astype(np.int64)
    fresh = np.concatenate([~p.tried[i] for p, i in pools])
    if classes is None:
        classes = np.unique(sign_class[fresh])
    for t, i in where:
        m.state.mark_tried(t, i)  # every one of them is a seed now, or was before
    have, count = np.unique(sign_class, return_counts=True)
    enough = have[count >= m.config.init.min_rays]  # fewer rays: propose makes nothing
    if np.intersect1d(enough, classes).size == 0:
        m.tally("init_too_few", 1)
        return set()  # nothing to try: no ray gathered or converted
    obs = type(pools[0][0].obs).concat([p.obs.take(i) for p, i in pools])
    received = max(float(p.received_at[i].max()) for p, i in pools)
    # the tile's own pool rows from its kept conversions, the neighbours' converted here
    parts = [
        pool_rays(m, t, i) if t == tile else to_local(frame, p.obs.take(i))
        for (t, i), (p, _i) in zip(where, pools, strict=True)
    ]
    rays = local_rays(
        obs,
        np.concatenate([r.origin for r in parts]),
        np.concatenate([r.direction for r in parts]),
    )
    created: set[int] = set()
    attempted = False
    used = np.zeros(len(rays), bool)
    for cls in np.intersect1d(enough, classes):
        idx = np.flatnonzero(rays.sign_class == cls)
        sub = rays.take(idx)
        cap = m.config.init_reseed_max
        seeds = seeds_of(sub, fresh[idx] if 0 < cap < idx.size else None)
        if 0 < cap < idx.size:
            m.tally("init_new_seeds_only", 1)
        if idx.size >= m.config.init.min_rays and seeds.size:
            attempted = True
            m.tally("init_rays", idx.size)
            m.tally("init_seeds", seeds.size)
        for cand in propose(sub, m.config.gate, m.config.init, seeds):
            members = idx[cand.members]
            lat, lon, h = frame.to_geodetic(cand.x[None])
            home_tile = str(quadkeys_of(lat, lon, m.zoom)[0])
            if not in_region(home_tile, m.region):
                home_tile = tile
            lm = create(m, home_tile, int(cls), frame.to_ecef(cand.x[None])[0], cand.cov)
            out = m.out[lm.home]
            out.created.append((lm.id, int(cls), float(lat[0]), float(lon[0]), float(h[0])))
            here = (tile, rays.take(members))
            link(m, obs.take(members), [lm] * len(members), vehicle, pass_id, received, here)
            used[members] = True
            created.add(lm.id)
    drop_used(m, where, used)
    if budget is not None and (created or attempted):
        _note_attempt(m, vehicle, pass_id, bool(created))
    if created:
        m.tally("created", len(created))
        adopt(m, area, [m.state.landmarks[i] for i in sorted(created)])
    return created


def over_budget(m: Matching, tile: str, vehicle: str, pass_id: int) -> bool:
    """Whether the pass's waiting rays in ``tile`` or the vehicle's exceed their budgets
    (``pending_max_per_pass``, ``pending_max_per_vehicle``): what :func:`enforce_budget`
    would evict from."""
    cfg = m.config
    p = m.state.pending.get(tile)
    if p is None:
        return False
    if cfg.pending_max_per_vehicle > 0 and p.per_vehicle[vehicle] > cfg.pending_max_per_vehicle:
        return True
    key = pass_key(vehicle, pass_id)
    return cfg.pending_max_per_pass > 0 and p.count_of(key) > cfg.pending_max_per_pass


def quarantined(m: Matching, vehicle: str, pass_id: int) -> bool:
    """Whether the pass is quarantined (:func:`initiate` makes nothing of its rays)."""
    b = m.state.passes.get(pass_key(vehicle, pass_id))
    return b is not None and bool(b.quarantined)


def initiate_waiting(m: Matching) -> set[int]:
    """At the end of a gating tick: :func:`initiate` for every pass with rays pooled in
    the tick and not yet tried as seeds, by tile (in order) and pass (by :func:`pass_key`),
    each over its tile's area with the classes of its untried rays in it; then its budgets
    (:func:`enforce_budget`). Returns the new landmarks' ids.

    Deferred to the tick's end so that a pass's rays of all the tick's uploads are tried
    together (one attempt a pass and tile, not one an upload); the order depends on the
    pool only, so live, bulk and replayed runs try the same rays in the same order."""
    born: set[int] = set()
    for tile in m.state.take_untried_tiles():
        p = m.state.pending.get(tile)
        while p is not None and not p.tried.all():
            # initiate marks every ray of the pass around the tile tried: the loop ends
            untried = np.flatnonzero(~p.tried)
            row = int(untried[np.argmin(p.key[untried])])
            vehicle, pass_id = p.vehicle[row], int(p.pass_id[row])
            born |= initiate(m, tile, m.area(tile), vehicle, pass_id)
            enforce_budget(m, tile, vehicle, pass_id, touch=False)
            p = m.state.pending.get(tile)
    return born


def _note_attempt(m: Matching, vehicle: str, pass_id: int, made: bool) -> None:
    """An initiation attempt of a pass with a budget record: it made a landmark (the count
    of failures starts again) or not (``quarantine_after`` in a row: quarantined)."""
    b = m.state.budget_of(vehicle, pass_id)
    b.failed = 0 if made else b.failed + 1
    after = m.config.quarantine_after
    if not made and after > 0 and b.failed >= after:
        b.quarantined = NO_LANDMARK
        m.tally("passes_quarantined", 1)
        m.tally(f"passes_quarantined.{NO_LANDMARK}", 1)


def adopt(m: Matching, area: list[str], new: list[Landmark]) -> None:
    """Offer pending rays of other passes to freshly created landmarks: in each tile of
    ``area`` (in order) the waiting rays of each (vehicle, pass) are a unit associated with
    the new landmarks, and the rays it links are taken from the pool. The units of all the
    tiles are associated in one call (each as alone:
    :func:`~hdmap.mapping.batch_association.associate_units`)."""
    g = m.config.gate
    cls = np.array([c.cls for c in new], np.int64)
    cov = np.array([c.cov for c in new])
    x_ecef = np.array([c.x for c in new])
    offers = []  # (tile, pool rows offered, their local rays, units (vehicle, pass, rows))
    inputs: list[UnitInput] = []
    for t in area:
        p = m.state.pending.get(t)
        if p is None or not len(p):
            continue
        # only rays of the new landmarks' classes can match (associate pairs same-class
        # only): select them first, convert them once
        cand = np.flatnonzero(np.isin(p.obs.sign_class, cls))
        if cand.size == 0:
            continue
        x = m.frames(t).from_ecef(x_ecef)
        local = pool_rays(m, t, cand)
        # a unit none of whose rays passes the wide gate (the first step of associate)
        # cannot be associated: offer only the others (exact, and the pool can be large)
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
        units = [u for u in units if live[u[2]].any()]
        offers.append((t, cand, local, units))
        inputs += [UnitInput(local.take(js), x, cov, cls) for _v, _pid, js in units]
    results = iter(associate_units(inputs, g))
    for t, cand, local, units in offers:
        p = m.state.pending[t]
        take = np.zeros(len(p), bool)
        for v, pid, js in units:
            res = next(results)
            hit = res.landmark >= 0
            if not hit.any():
                continue
            sel = cand[js]
            take[sel[hit]] = True
            rec = float(p.received_at[sel[hit]].max())
            lms = [new[k] for k in res.landmark[hit]]
            link(m, p.obs.take(sel[hit]), lms, v, pid, rec, (t, local.take(js[hit])))
            m.tally("adopted", int(hit.sum()))
        m.state.drop_pending(t, take)


def pool_rays(m: Matching, tile: str, rows: np.ndarray) -> LocalRays:
    """The rows ``rows`` of ``tile``'s pool as rays in the tile's frame (:func:`to_local`),
    from the pool's kept conversions (:attr:`~hdmap.mapping.landmarks.PendingTile.local`),
    converting and keeping those it has not."""
    p = m.state.pending[tile]
    have = p.local[rows]
    todo = np.flatnonzero(np.isnan(have[:, 0]))
    if todo.size:
        fresh = to_local(m.frames(tile), p.obs.take(rows[todo]))
        have[todo, :3], have[todo, 3:] = fresh.origin, fresh.direction
        p.local[rows[todo]] = have[todo]
    return local_rays(p.obs.take(rows), have[:, :3], have[:, 3:])


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
    """Drop pending rays captured more than ``pending_ttl_s`` before the matcher's clock
    (event time); returns how many."""
    cutoff = m.now - m.config.pending_ttl_s
    n = 0
    for t, p in list(m.state.pending.items()):
        old = p.added_at < cutoff
        if old.any():
            m.state.drop_pending(t, old)
            n += int(old.sum())
    return n


def forget_budgets(m: Matching) -> int:
    """Drop the budget records of passes silent for ``pending_ttl_s`` (their rays have
    expired: nothing of the pass is left to budget); returns how many."""
    cutoff = m.now - m.config.pending_ttl_s
    gone = [k for k, b in m.state.passes.items() if b.last_at < cutoff]
    m.state.drop_budgets(gone)
    return len(gone)
