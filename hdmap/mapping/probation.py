"""Vehicles leaving probation in the matcher: their held passes count in full (promoted),
go (caught), or, for a vehicle that stopped driving while on probation, go in at the
probation weight. The gating sums change here; the solvers change through the assoc
output of every home tile the vehicle has held passes in.
"""

from __future__ import annotations

import logging

import numpy as np

from hdmap.mapping import presence
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import refresh_due
from hdmap.mapping.matching import Matching
from hdmap.mapping.trust import CAUGHT, VehicleTrust
from schemas.ids import hold_key

log = logging.getLogger(__name__)


def settle(m: Matching, vehicle: str, t: VehicleTrust) -> set[int]:
    """A vehicle leaves probation: its held passes count in full (promoted) or go
    (caught), here and, through the assoc output of every home tile it has held passes
    in, in the solvers. Returns the landmarks that went with them."""
    ref = m.fleet_ref()
    status = t.settle(m.config.trust, ref)
    if status is None:
        return set()
    log.info(
        "vehicle %s %s after %d passes (offset chi2 %.2f, mean offset %s m)",
        vehicle,
        "caught" if status == CAUGHT else "promoted",
        t.passes,
        t.chi2(ref),
        np.round(t.mean_offset(ref), 2).tolist(),
    )
    if status == CAUGHT:
        m.tally("vehicles_caught", 1)
        presence.release_held(m, vehicle, weigh=False)
        return let_go(m, vehicle, t, True, 0.0)
    m.tally("vehicles_promoted", 1)
    gone = let_go(m, vehicle, t, False, t.weight(m.config.trust, ref))
    presence.release_held(m, vehicle, weigh=True)
    return gone


def freeze_stale(m: Matching, now: float) -> int:
    """Vehicles on probation that stopped driving before they could be settled (none for
    ``probation_ttl_s`` of event time before ``now``): their held passes go in at the
    probation weight. Looks at the vehicles with held passes due only (and at those seen
    since they were filed, once: :class:`~hdmap.mapping.trust.SeenIndex`), not at every
    trust record. Returns how many were let go."""
    cfg = m.config.trust
    cutoff = now - cfg.probation_ttl_s
    n = 0
    by_row: dict[int, Landmark] | None = None  # built once, if anyone is due: releases
    # empty no landmark, so it stays right for every vehicle let go here
    for v in m.state.held_by_seen.due(cutoff, m.state.last_seen):
        t = m.state.trust.get(v)
        if t is None or not t.held_homes or not t.held(cfg):
            continue  # nothing held, or settled otherwise (probation turned off)
        m.state.trust_of(v)  # marks it for saving
        w = t.weight(cfg, m.fleet_ref())
        local = w / cfg.probation_weight if m.config.gate_probation_full else w
        if by_row is None:
            by_row = landmarks_by_row(m)
        let_go(m, v, t, False, w, local, by_row)
        presence.release_held(m, v, weigh=False)
        m.tally("probation_timed_out", 1)
        n += 1
    return n


def forget_quiet(m: Matching, now: float) -> int:
    """Forget the trust records of vehicles not seen for ``forget_after_s`` of event time
    before ``now`` (``TrustConfig.forget_after_s``; counted ``trust_forgotten``): one that
    returns is new (on probation again). A vehicle with held passes keeps its record (the
    probation time-out lets them go first) and is looked at again ``forget_after_s``
    later. Looks at the vehicles due only. Returns how many were forgotten."""
    after = m.config.trust.forget_after_s
    if after <= 0:
        return 0
    n = 0
    for v in m.state.all_by_seen.due(now - after, m.state.last_seen):
        t = m.state.trust.get(v)
        if t is None:
            continue
        if t.held_homes:
            m.state.all_by_seen.add(v, now)
            continue
        m.state.forget_trust(v)
        m.fleet.forget(v)
        m.flagged.pop(v, None)
        n += 1
    if n:
        m.tally("trust_forgotten", n)
    return n


def follow_time(m: Matching) -> None:
    """What the matcher's clock (:attr:`Matching.now`) having moved settles: probation
    time-outs, then forgotten records. Run after each obs entry (the work is the
    vehicles due), so the outcome does not depend on how the entries were batched."""
    freeze_stale(m, m.now)
    forget_quiet(m, m.now)


def landmarks_by_row(m: Matching) -> dict[int, Landmark]:
    """The matcher's landmarks by their row in the gating sums."""
    return {lm.row: lm for lm in m.state.landmarks.values()}


def let_go(
    m: Matching,
    vehicle: str,
    t: VehicleTrust,
    dropped: bool,
    weight: float,
    local: float | None = None,
    by_row: dict[int, Landmark] | None = None,
) -> set[int]:
    """Settle ``vehicle``'s held passes here (dropped, or released at ``local``, default
    ``weight``) and, through the assoc output of every home tile it has held passes in, in
    the solvers (released at ``weight``). Returns the landmarks retired for having no rays
    left. ``by_row``: the landmarks by sums row, when the caller lets several vehicles go
    (built here otherwise)."""
    key = hold_key(vehicle)
    if dropped:
        rows = m.sums.drop_held(key)
    else:
        rows = m.sums.release(key, weight if local is None else local)
    for home in sorted(t.held_homes):
        out = m.out[home]
        out.trust.append((out.vehicle_index(vehicle), dropped, weight))
    t.held_homes.clear()
    m.state.held_by_seen.discard(vehicle)
    if not rows.size:
        return set()
    if by_row is None:
        by_row = landmarks_by_row(m)
    lms = [by_row[r] for r in rows.tolist() if r in by_row]
    empty = m.sums.n_obs([lm.row for lm in lms]) == 0
    gone = {lm.id for lm, e in zip(lms, empty, strict=True) if e}
    for lm in lms:
        if lm.id in gone:
            m.state.remove(lm)  # only the caught vehicle saw it
            m.out[lm.home].ended.append(lm.id)
            m.tally("emptied", 1)
    refresh_due(m, sorted(lm.id for lm in lms if lm.id not in gone))
    return gone
