"""Gating ticks: what a unit's association sees, and when the landmarks it touched are
re-solved and its waiting rays start landmarks.

Event time is cut into ticks of ``MatchingConfig.tick_s`` seconds. A unit belongs to the
tick of the matcher's clock (:meth:`hdmap.mapping.matching.Matching.entry_time`) when its
own event time is at most ``tick_lag_s`` (3 s) behind the clock, else to the tick of its
own event time (:func:`enter`); a run of consecutive units of one tick is a *gating tick*. Every
unit of it is associated with the landmarks as they stood when it began: the set of
landmarks, their gating estimates (position, covariance) and facings
(``Landmark.facing``). What the units do meanwhile accumulates: links go into the gating
sums, views and sightings are counted, the rays no landmark took wait in the pending pool.
When a unit of another tick comes, :func:`enter` ends the tick before that unit is
matched: :func:`end_tick` tries the tick's waiting rays as seeds of new landmarks, pass by
pass (:func:`hdmap.mapping.pending.initiate_waiting`; a new landmark is offered the
waiting rays of the other passes), checks the sightings of the landmarks the tick had in
view (retiring those not there), re-solves the gating estimates of those it touched or
started and offers them a merge.

Invariant: which units share a gating tick depends only on the entries (their order and
their event times), never on how they were batched, when they arrived or on a restart
(the tick's marks and its untried rays are saved with the table), so live processing, a
bulk upload a day late and a replay give the same map. Within a tick a unit's
association depends on the units before it only through its own vehicle's trust record
(the correction of a suspect vehicle's origins) and landmarks a vehicle's settlement
emptied: what :func:`hdmap.mapping.unit.signature` checks, and what lets the units of a
tick be associated together. No landmark is born inside a tick: a unit that leaves its
pass over its pending budget (:func:`hdmap.mapping.pending.over_budget`; an honest pass
uploaded whole into a tile without landmarks does) ends the tick after itself
(:func:`split_tick`: every waiting ray tried, this pass's with the others, then the
budget), and the units after it begin a new tick of the same index, seeing what it
started (docs/experiments/2026-12-tick-lag.md: what births inside a tick cost). A pass
that is quarantined does not end ticks (its attempts make nothing); one that floods a
tile ends a tick at most ``quarantine_after`` + 1 times.

Live traffic at a high rate puts hundreds of units in one tick (uploads seconds out of
order included: a lag of ``tick_s`` alone cut a load test's every second into 4-18
ticks, each straggler ending the live tick); an upload that comes late (a day's drives
sent at once) goes by its own event times, so its units do not pile into the live tick
(they would not see each other's new landmarks): where late and live entries interleave,
ticks are short, down to one unit. So are a pass's first tiles when it is uploaded at
its end (more than ``tick_lag_s`` behind the clock): see the pitfall of
``MatchingConfig.tick_lag_s`` for why the lag is not the length of a pass.

``tick_s = 0``: every unit is its own tick, ended at the end of the unit (initiation,
sightings, re-solve and merge after each unit, with a vehicle's settlement re-solving at
once): the matcher before ticks, to the bit.

Pitfalls: a sign first seen in a tick gets its landmark when the tick ends, from the
first of the tick's passes (by pass key) whose rays make one; the others' rays are
adopted, or start landmarks of their own (merged once both have ``merge_min_passes``)
where adoption's gate refuses them. The last tick's initiation, merges and re-solves wait
for the first entry of another tick (no timer ends a tick: it would make the map depend
on when entries arrived).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from hdmap.mapping.facing import Facing, angle_between
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import refresh
from hdmap.mapping.matching import Matching
from hdmap.mapping.merge import merge_touched
from hdmap.mapping.pending import initiate_waiting
from hdmap.mapping.sightings import SightingConfig, outshone, unseen

Array = NDArray[np.float64]


def tick_of(m: Matching, at: float, now: float) -> int | None:
    """The tick of a unit of event time ``at`` when the clock is at ``now``: the clock's when
    the unit is at most ``tick_lag_s`` behind it, else its own (index ``floor(t /
    tick_s)``; None with ``tick_s = 0``: every unit its own)."""
    step = m.config.tick_s
    if step <= 0:
        return None
    return math.floor((now if now - at <= m.config.tick_lag_s else at) / step)


def enter(m: Matching, at: float) -> None:
    """Put the unit of event time ``at`` in its tick (:func:`tick_of`, the clock already
    moved by it); when the current tick is another, it ends first (:func:`end_tick`). With
    ``tick_s = 0`` the unit ends its own tick (:func:`hdmap.mapping.unit.match_unit`)."""
    k = tick_of(m, at, m.now)
    if k is not None and k != m.state.tick_id:
        end_tick(m)
        m.state.start_tick(k)
        m.tick_serial += 1


def split_tick(m: Matching) -> None:
    """End the current tick here (:func:`end_tick`) and go on with a new one of the same
    index: a pass over its pending budget inside a tick (counted ``tick_split``)."""
    end_tick(m)
    assert m.state.tick_id is not None  # a unit is in a tick (tick_s > 0)
    m.state.start_tick(m.state.tick_id)
    m.tick_serial += 1
    m.tally("tick_split", 1)


@dataclass(frozen=True)
class Candidates:
    """Landmarks a unit sees and what association takes of them, as arrays in the unit's
    tile frame: gating positions, covariances, classes and facings (row ``k``: ``lms[k]``)."""

    lms: list[Landmark]
    x: Array
    cov: Array
    cls: NDArray[np.int64]
    facing: Facing
    scale: Array


def candidates(m: Matching, tile: str) -> Candidates:
    """The landmarks filed under ``tile``'s area (by id), as the tick found them, as arrays
    in the tile's frame. A tile's arrays are built once and kept while the landmarks'
    ``gating_version`` stays (within a gating tick, until a landmark is started, removed
    or re-solved); a conversion's rows do not depend on the rows converted with them, so
    kept rows are the ones building them anew gives."""
    hit = m.candidate_arrays.get(tile)
    if hit is None or hit[0] != m.state.gating_version:
        lms = m.state.near(m.area(tile))
        x = np.array([lm.x for lm in lms]).reshape(-1, 3)
        built = Candidates(
            lms,
            m.frames(tile).from_ecef(x).reshape(-1, 3),
            np.array([lm.cov for lm in lms]).reshape(-1, 3, 3),
            np.array([lm.cls for lm in lms], np.int64),
            gating_facings(lms),
            np.array([lm.scale for lm in lms], float),
        )
        hit = m.candidate_arrays[tile] = (m.state.gating_version, built)
    c: Candidates = hit[1]
    return c


def gating_facings(lms: list[Landmark]) -> Facing:
    """The landmarks' facings as association sees them (as of their last re-solve), with
    the second streets merged in."""
    f = Facing.from_rows([lm.facing for lm in lms])
    second = np.array([lm.second_facing for lm in lms], float)
    return replace(f, second=second) if np.isfinite(second).any() else f


def end_tick(m: Matching) -> None:
    """The tick is over: its waiting rays start landmarks
    (:func:`hdmap.mapping.pending.initiate_waiting`), the landmarks it had in view that its
    passes do not detect retire (:mod:`hdmap.mapping.sightings`, counted
    ``retired_unseen``), those it touched or started have their gating estimates re-solved
    and are offered a merge."""
    born = initiate_waiting(m)
    m.state.tick_touched |= born
    touched, counted = m.state.take_tick()
    gone = retire_unseen(m, counted) if m.config.sightings.enabled else set()
    ids = [i for i in touched if i not in gone and i in m.state.landmarks]
    refresh(m, ids)
    merge_touched(m, ids)


def retire_unseen(m: Matching, ids: list[int]) -> set[int]:
    """Retire the landmarks of ``ids`` whose sightings say they are not there, alone or
    against a same-class neighbour seen from the same side; returns them."""
    cfg = m.config.sightings
    gone: set[int] = set()
    for lid in ids:
        lm = m.state.landmarks.get(lid)
        if lm is None:
            continue
        if unseen(lm.seen, lm.in_view, cfg):
            m.tally("retired_unseen", 1)
        elif _outshone(m, lm, cfg):
            m.tally("retired_outshone", 1)
        else:
            continue
        m.state.remove(lm)
        m.out[lm.home].ended.append(lm.id)
        gone.add(lm.id)
    return gone


def _outshone(m: Matching, lm: Landmark, cfg: SightingConfig) -> bool:
    """:func:`hdmap.mapping.sightings.outshone` against the landmarks of ``lm``'s class
    within ``rel_radius_m`` whose facing (known, as ``lm``'s) is within ``rel_max_deg``."""
    if cfg.rel_share <= 0.0 or lm.in_view < cfg.min_in_view or lm.facing[3] <= 0.0:
        return False
    if lm.seen >= cfg.rel_share * lm.in_view:
        return False  # no neighbour's share bound exceeds 1: most landmarks stop here
    others = [
        o
        for o in m.state.near(m.area(lm.tile))  # the tile and its neighbours: > 50 m around
        if o.cls == lm.cls and o.id != lm.id and o.in_view >= cfg.min_in_view
        and o.facing[3] > 0.0
    ]  # fmt: skip
    if not others:
        return False
    x = np.array([o.x for o in others])
    near = np.linalg.norm(x - lm.x, axis=1) <= cfg.rel_radius_m
    apart = angle_between([o.facing[0] for o in others], lm.facing[0])
    keep = near & (apart <= np.radians(cfg.rel_max_deg))
    if not keep.any():
        return False
    idx = np.flatnonzero(keep)
    return outshone(
        lm.seen, lm.in_view, [others[k].seen for k in idx], [others[k].in_view for k in idx], cfg
    )
