"""Gating ticks: what a unit's association sees, and when the landmarks it touched are
re-solved.

Event time is cut into ticks of ``MatchingConfig.tick_s`` seconds. A unit belongs to the
tick of the matcher's clock (:meth:`hdmap.mapping.matching.Matching.entry_time`) when its
own event time is at most ``tick_s`` behind the clock, else to the tick of its own event
time (:func:`enter`); a run of consecutive units of one tick is a *gating tick*. Every
unit of it is associated with the landmarks as they stood when it began: the set of
landmarks, their gating estimates (position, covariance) and facings
(``Landmark.facing``), plus the landmarks its own pass started in it. What the units do
meanwhile accumulates: links go into the gating sums, views and sightings are counted, new
landmarks adopt pending rays. When a unit of another tick comes, :func:`enter` ends the
tick before that unit is matched: :func:`end_tick` checks the sightings of the landmarks
it had in view (retiring those not there), re-solves the gating estimates of those it
touched and offers them a merge.

Invariant: which units share a gating tick depends only on the entries (their order and
their event times), never on how they were batched, when they arrived or on a restart
(the tick's marks are saved with the table), so live processing, a bulk upload a day late
and a replay give the same map. Within a tick a unit's association depends on the units
before it only through its own pass's new landmarks, its own vehicle's trust record (the
correction of a suspect vehicle's origins) and landmarks a vehicle's settlement emptied:
what :func:`hdmap.mapping.unit.signature` checks, and what lets the units of a tick be
associated together.

Live traffic at a high rate puts hundreds of units in one tick (uploads a little out of
order included); an upload that comes late (a day's drives sent at once) goes by its own
event times, so its units do not pile into the live tick (they would not see each other's
new landmarks): where late and live entries interleave, ticks are short, down to one unit.

``tick_s = 0``: every unit is its own tick, ended at the end of the unit (sightings,
re-solve and merge after each unit, with a vehicle's settlement re-solving at once): the
matcher before ticks, to the bit.

Pitfalls: a landmark started by one pass is not a candidate for another pass's rays until
the tick ends (the other pass's rays wait in the pool, and may start a second landmark of
the sign, merged once both have ``merge_min_passes``); the last tick's merges and
re-solves wait for the first entry of another tick (no timer ends a tick: it would make
the map depend on when entries arrived).
"""

from __future__ import annotations

import math

from hdmap.mapping.facing import Facing
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import refresh
from hdmap.mapping.matching import Matching
from hdmap.mapping.merge import merge_touched
from hdmap.mapping.sightings import unseen


def tick_of(m: Matching, at: float, now: float) -> int | None:
    """The tick of a unit of event time ``at`` when the clock is at ``now``: the clock's when
    the unit is at most ``tick_s`` behind it, else its own (index ``floor(t / tick_s)``;
    None with ``tick_s = 0``: every unit its own)."""
    step = m.config.tick_s
    if step <= 0:
        return None
    return math.floor((now if now - at <= step else at) / step)


def enter(m: Matching, at: float) -> None:
    """Put the unit of event time ``at`` in its tick (:func:`tick_of`, the clock already
    moved by it); when the current tick is another, it ends first (:func:`end_tick`). With
    ``tick_s = 0`` the unit ends its own tick (:func:`hdmap.mapping.unit.match_unit`)."""
    k = tick_of(m, at, m.now)
    if k is not None and k != m.state.tick_id:
        end_tick(m)
        m.state.start_tick(k)
        m.tick_serial += 1


def visible(m: Matching, area: list[str], key: int) -> list[Landmark]:
    """The landmarks filed under ``area`` (by id) that a unit of pass ``key`` sees: those
    there when the tick began and those the pass started in it."""
    born = m.state.tick_born
    lms = m.state.near(area)
    if not born:
        return lms
    return [lm for lm in lms if born.get(lm.id, key) == key]


def gating_facings(lms: list[Landmark]) -> Facing:
    """The landmarks' facings as association sees them (as of their last re-solve)."""
    return Facing.from_rows([lm.facing for lm in lms])


def end_tick(m: Matching) -> None:
    """The tick is over: retire the landmarks it had in view that its passes do not detect
    (:mod:`hdmap.mapping.sightings`, counted ``retired_unseen``), re-solve the gating
    estimates of those it touched and offer them a merge."""
    touched, counted = m.state.take_tick()
    gone = retire_unseen(m, counted) if m.config.sightings.enabled else set()
    ids = [i for i in touched if i not in gone and i in m.state.landmarks]
    refresh(m, ids)
    merge_touched(m, ids)


def retire_unseen(m: Matching, ids: list[int]) -> set[int]:
    """Retire the landmarks of ``ids`` whose sightings say they are not there; returns them."""
    gone: set[int] = set()
    for lid in ids:
        lm = m.state.landmarks.get(lid)
        if lm is None or not unseen(lm.seen, lm.in_view, m.config.sightings):
            continue
        m.state.remove(lm)
        m.out[lm.home].ended.append(lm.id)
        m.tally("retired_unseen", 1)
        gone.add(lm.id)
    return gone
