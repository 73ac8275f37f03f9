"""The map follows the world (issue 21): each landmark's existence, moved by the passes
that detect it and by the vehicles' reports of mapped signs they had in view and did not
detect (``ObsGroup.absences``, :mod:`vehicle.absence`); a landmark whose existence falls
to revoked leaves the map (a retirement without successor: a tombstone in the deltas;
its id is never given again).

Evidence, per landmark and pass (:mod:`hdmap.mapping.existence` for the arithmetic):

- **Seen**: a pass's rays were linked to it. Counted when the pass first links rays to it
  (:meth:`hdmap.mapping.quiet.QuietPasses.members`: a pass counts once however many units
  and batches its rays come in); its latest ray's time becomes ``last_seen``.
- **Not seen**: the pass's vehicle reported it absent, with the frames it had it in view.
  Counted unless the pass linked rays to it (seen wins), the pass is blind (it saw less
  than half of what it had in view: :func:`hdmap.mapping.evidence.blind`) or the
  vehicle's misses of it are over their cap. A vehicle on probation has its reports held
  (counted ``absences_held``, kept with the table) until it leaves probation: promoted,
  they are weighed then (:func:`release_held`); caught or timed out, they go.

A landmark is revoked only when its log-odds reach ``l_revoked`` *and* misses of at
least ``min_vehicles`` vehicles have counted since it was last seen; otherwise it stays
just above (doubtful), so one vehicle cannot take a sign off the map whatever it reports.

Invariant: evidence is applied in log order at the entry that carries it (rays when they
are linked, absences with their entry), never on a timer, so a replay gives the map live
processing gave. Pitfall: evidence is weighed in arrival order, not capture order: a bulk
upload of old passes that saw a sign, arriving after the passes that found it gone, moves
it back up (the clamp bounds how far).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdmap.mapping.evidence import EvidencePolicy, blind
from hdmap.mapping.existence import CONFIRMED, ExistenceConfig, status, update
from hdmap.mapping.landmarks import Landmark
from schemas.ids import pass_key

EXIST_CONFIRMED, EXIST_DOUBTFUL = 1, 2
"""Published states, the values of ``schemas.tables.EXIST_CONFIRMED`` and
``EXIST_DOUBTFUL`` (the domain does not import the codec: ``tests/unit/test_presence.py``
checks they agree); revoked ones are retired."""


@dataclass(frozen=True)
class PresenceConfig:
    """Existence per landmark (:mod:`hdmap.mapping.existence`) and the bounds on what a
    vehicle's "not seen" reports may do (:mod:`hdmap.mapping.evidence`)."""

    enabled: bool = True
    existence: ExistenceConfig = field(default_factory=ExistenceConfig)
    evidence: EvidencePolicy = field(default_factory=EvidencePolicy)


def log_odds(lm: Landmark, cfg: ExistenceConfig) -> float:
    """A landmark's existence log-odds (a new one stands at ``l_confirmed``)."""
    return cfg.l_confirmed if math.isnan(lm.exist) else lm.exist


def row(lm: Landmark, cfg: ExistenceConfig) -> tuple[int, float, int, float, float]:
    """What the solver publishes of a landmark's existence: (id, probability, state,
    first seen, last seen)."""
    lo = log_odds(lm, cfg)
    state = EXIST_CONFIRMED if status(lo, cfg) == CONFIRMED else EXIST_DOUBTFUL
    p = 1.0 / (1.0 + math.exp(-lo))
    return lm.id, p, state, lm.created_at, lm.last_seen or lm.created_at


def seen(m: Any, vehicle: str, lms: list[Landmark], t: float) -> None:
    """Rays of a pass of ``vehicle`` at event time ``t`` were linked to ``lms`` (each new to
    the pass: the caller checks the pass's members)."""
    cfg: PresenceConfig = m.config.presence
    if not cfg.enabled or not lms:
        return
    ex = cfg.existence
    lo = np.array([log_odds(lm, ex) for lm in lms])
    new = update(lo, np.ones(lo.size, bool), np.full(lo.size, ex.full_frames), ex)
    for lm, value in zip(lms, new.tolist(), strict=True):
        lm.exist = value
        lm.last_seen = max(lm.last_seen, t)
        m.state.misses.admit(lm.id, vehicle, t, seen=True)
        m.out[lm.home].existence[lm.id] = row(lm, ex)
    m.state.mark_changed([lm.id for lm in lms])
    m.tally("passes_seen", len(lms))


def not_seen(m: Any, vehicle: str, pass_id: int, key: int, absences: Any, held: bool) -> None:
    """Pass ``pass_id`` (cluster key ``key``) of ``vehicle`` reported ``absences`` (columns
    ``landmark_id``, ``t``, ``frames``: :class:`schemas.tables.Absences`): count what
    counts (module docstring), revoke what falls to revoked with enough vehicles behind
    it; ``held``: the vehicle is on probation, the reports wait (:func:`release_held`)."""
    cfg: PresenceConfig = m.config.presence
    if not cfg.enabled or not len(absences.landmark_id):
        return
    ids = np.asarray(absences.landmark_id, np.uint64).tolist()
    lms = [m.state.landmarks.get(i) for i in ids]
    known = [k for k, lm in enumerate(lms) if lm is not None]
    if len(known) < len(ids):
        m.tally("absences_unknown", len(ids) - len(known))
    if held:
        m.state.hold_absences(
            vehicle,
            [(pass_id, ids[k], float(absences.t[k]), int(absences.frames[k])) for k in known],
        )
        m.tally("absences_held", len(known))
        return
    linked = m.quiet.members(key)
    contradicted = [k for k in known if ids[k] in linked]
    if contradicted:
        m.tally("absences_contradicted", len(contradicted))
    todo = [k for k in known if ids[k] not in linked]
    if not todo:
        return
    flags = [True] * len(linked) + [False] * len(todo)
    if blind(flags, cfg.evidence)[0]:
        m.tally("absences_blind", len(todo))
        return
    ex, ledger = cfg.existence, m.state.misses
    for k in todo:
        lm, t = lms[k], float(absences.t[k])
        assert lm is not None
        if not ledger.admit(lm.id, vehicle, t, seen=False):
            m.tally("absences_capped", 1)
            continue
        lo = float(update([log_odds(lm, ex)], [False], [int(absences.frames[k])], ex)[0])
        if lo <= ex.l_revoked and not ledger.revocable(lm.id):
            lo = min(log_odds(lm, ex), math.nextafter(ex.l_revoked, math.inf))
            m.tally("revocations_deferred", 1)
        m.tally("absences_counted", 1)
        if lo <= ex.l_revoked:
            revoke(m, lm)
            continue
        lm.exist = lo
        m.state.mark_changed([lm.id])
        m.out[lm.home].existence[lm.id] = row(lm, ex)


def release_held(m: Any, vehicle: str, weigh: bool) -> None:
    """``vehicle`` left probation: its held reports are weighed now, pass by pass in the
    order they came (``weigh``: promoted), or go (caught, timed out)."""
    held = m.state.take_held_absences(vehicle)
    if not weigh or not held:
        return
    by_pass: dict[int, list[tuple[int, float, int]]] = {}
    for pass_id, lid, t, frames in held:
        by_pass.setdefault(pass_id, []).append((lid, t, frames))
    for pass_id, rows in by_pass.items():
        cols = _Reports(
            np.array([r[0] for r in rows], np.uint64),
            np.array([r[1] for r in rows], float),
            np.array([r[2] for r in rows], np.int64),
        )
        not_seen(m, vehicle, pass_id, pass_key(vehicle, pass_id, True), cols, held=False)


@dataclass(frozen=True)
class _Reports:
    """Held reports of one pass, in the columns :func:`not_seen` reads."""

    landmark_id: np.ndarray
    t: np.ndarray
    frames: np.ndarray


def revoke(m: Any, lm: Landmark) -> None:
    """``lm`` is gone from the world: it leaves the map (retired without successor)."""
    m.state.remove(lm)
    m.state.misses.forget(lm.id)
    out = m.out[lm.home]
    out.existence.pop(lm.id, None)
    out.ended.append(lm.id)
    m.tally("revoked", 1)
