"""One unit through the matcher: one vehicle pass's rays for one tile.

1. :func:`prepare_unit`: a suspect vehicle's origins are moved by its mean offset, its
   track labels checked; rays into the tile's ENU frame; the candidate landmarks of the
   tile and its 8 neighbours (so a sign near a border is one landmark) as the gating tick
   found them (:func:`hdmap.mapping.tick.candidates`, with their gating facings);
2. :func:`associate_prepared` (gate, per-pass offset, per-image assignment; the units of
   one tick together, :mod:`hdmap.mapping.batch_association`), then :func:`group_check`;
   the pass's offset goes into the vehicle's trust record, which may settle its probation
   (:func:`hdmap.mapping.probation.settle`);
3. :func:`match_unit`: matched rays are linked (:func:`hdmap.mapping.linking.link`);
   unmatched rays join the pending pool, where they are tried as seeds of new landmarks
   with the tick's other rays of the pass when the tick ends
   (:func:`hdmap.mapping.pending.initiate_waiting`); a unit that leaves the pass or the
   vehicle over its pending budget ends the tick after itself
   (:func:`hdmap.mapping.tick.split_tick`, then
   :func:`hdmap.mapping.pending.enforce_budget`: what a pass pools stays bounded);
4. the candidates the unit had in view count a sighting; what it touched, had in view and
   started is noted for the end of the gating tick (:mod:`hdmap.mapping.tick`: initiation,
   sightings checked, gating estimates re-solved, merges), at once with ``tick_s = 0``.

Invariant: a unit's association depends on its rays, the tick's landmark estimates and
:func:`signature` (its vehicle's correction, its candidates) only; one computed earlier in
the tick for the same signature is the one it would get now.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from hdmap.mapping.association import Association, LocalRays, valid_tracks
from hdmap.mapping.batch_association import UnitInput, associate_units
from hdmap.mapping.initiation import triangulate_groups
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import link, to_local
from hdmap.mapping.matching import Matching
from hdmap.mapping.pending import (
    enforce_budget,
    initiate,
    over_budget,
    quarantined,
    touch_budget,
)
from hdmap.mapping.probation import settle
from hdmap.mapping.sightings import in_view
from hdmap.mapping.tick import candidates, end_tick, gating_facings, split_tick
from hdmap.mapping.trust import VehicleTrust


def shift_origins(frame: Any, obs: Any, d_en: np.ndarray) -> Any:
    """The same observations with origins moved by ``d_en`` (East, North metres)."""
    x = frame.from_geodetic(obs.lat, obs.lon, obs.h)
    x[:, :2] += np.asarray(d_en, float)[:2]
    lat, lon, h = frame.to_geodetic(x)
    return replace(obs, lat=lat, lon=lon, h=h)


def correction(m: Matching, vehicle: str) -> np.ndarray:
    """The offset taken out of the vehicle's origins (East, North): its mean offset while it
    is suspect, else zero. Reads its trust record, changes nothing."""
    ref = m.fleet_ref()
    trust = m.state.trust.get(vehicle)
    if trust is not None and trust.suspect(m.config.trust, ref):
        return np.asarray(trust.mean_offset(ref), float)
    return np.zeros(2)


def _corrected(m: Matching, frame: Any, obs: Any, vehicle: str) -> tuple[Any, np.ndarray, int]:
    """``obs`` with the vehicle's :func:`correction` taken out and its track labels checked;
    also the correction and the rays whose track was invalid."""
    applied = correction(m, vehicle)
    if applied.any():
        obs = shift_origins(frame, obs, applied)
    invalid = 0
    if obs.track.any():  # the vehicle's labels are checked once, as they come in
        track = valid_tracks(obs.track, obs.image).astype(np.uint32)
        invalid = int((obs.track != track).sum())
        obs = replace(obs, track=track)
    return obs, applied, invalid


@dataclass(frozen=True)
class Prepared:
    """A unit made ready for association: its rays (corrected, in its tile's frame) and the
    candidate landmarks it sees (:func:`hdmap.mapping.tick.candidates`)."""

    tile: str
    vehicle: str
    pass_id: int
    obs: Any
    """The corrected observations."""
    applied: np.ndarray
    """The suspect vehicle's offset taken out (East, North)."""
    track_invalid: int
    rays: LocalRays
    area: list[str]
    cands: list[Landmark]
    input: UnitInput | None
    """What association takes (None: no candidate)."""

    @property
    def signature(self) -> tuple[bytes, tuple[int, ...]]:
        """What the association depends on besides the tick's landmark estimates: the
        offset taken out and the candidates (:func:`signature`)."""
        return _signature(self.applied, self.cands)


def signature(m: Matching, tile: str, vehicle: str) -> tuple[bytes, tuple[int, ...]]:
    """What a unit's association depends on besides its rays and the landmark estimates of
    its tick (fixed while the tick lasts): the correction of its vehicle's origins and its
    candidates. A unit prepared earlier in the tick with the same signature is prepared
    as it would be now, and its association is the one it would get now."""
    return _signature(correction(m, vehicle), candidates(m, tile).lms)


def _signature(applied: np.ndarray, cands: list[Landmark]) -> tuple[bytes, tuple[int, ...]]:
    return applied.tobytes(), tuple(c.id for c in cands)


def prepare_unit(m: Matching, tile: str, vehicle: str, pass_id: int, obs: Any) -> Prepared:
    """The unit of ``vehicle``'s pass ``pass_id`` in ``tile`` with rays ``obs`` (an
    observation table), ready to associate (reads the state, changes nothing)."""
    (u,) = prepare_units(m, [(tile, vehicle, pass_id, obs)])
    return u


def prepare_units(m: Matching, units: list[tuple[str, str, int, Any]]) -> list[Prepared]:
    """:func:`prepare_unit` of each (tile, vehicle, pass, rays), the rays of the units of
    one tile converted into its frame in one call (a conversion's rows do not depend on
    the rows converted with them: the rays each unit gets alone)."""
    fixed = [_corrected(m, m.frames(t), obs, v) for t, v, _p, obs in units]
    by_tile: dict[str, list[int]] = {}
    for k, (t, *_rest) in enumerate(units):
        by_tile.setdefault(t, []).append(k)
    rays: dict[int, LocalRays] = {}
    for t, ks in by_tile.items():
        both = to_local(m.frames(t), type(fixed[ks[0]][0]).concat([fixed[k][0] for k in ks]))
        start = 0
        for k in ks:
            n = len(fixed[k][0])
            part = both.take(np.arange(start, start + n))
            # a unit none of whose rays is tracked has no track column (as alone)
            rays[k] = part if fixed[k][0].track.any() else replace(part, track=None)
            start += n
    out = []
    for k, (t, v, pid, _obs) in enumerate(units):
        obs, applied, invalid = fixed[k]
        c = candidates(m, t)
        unit_input = UnitInput(rays[k], c.x, c.cov, c.cls, c.facing, c.scale) if c.lms else None
        area = m.area(t)
        out.append(Prepared(t, v, pid, obs, applied, invalid, rays[k], area, c.lms, unit_input))
    return out


@dataclass(frozen=True)
class Checked:
    """A unit's association and its group check (:func:`group_checks`)."""

    res: Association
    matched: np.ndarray
    """``res.landmark`` without the groups whose rays meet elsewhere."""
    rejected: int
    """Rays the group check took out (counted ``group_rejected`` when the unit is matched)."""


def associate_prepared(m: Matching, units: list[Prepared]) -> list[Checked | None]:
    """The associations of ``units``, group-checked (None where a unit has no candidate),
    computed together (:func:`hdmap.mapping.batch_association.associate_units`,
    :func:`group_checks`: each as alone)."""
    todo = [(u.rays, u.input) for u in units if u.input is not None]
    results = associate_units(
        [i for _r, i in todo], m.config.gate, m.config.estimator.panel_rel_sigma
    )
    checks = group_checks(
        m, [(rays, r, i.x, i.cov) for (rays, i), r in zip(todo, results, strict=True)]
    )
    done = iter(Checked(r, o, k) for r, (o, k) in zip(results, checks, strict=True))
    return [None if u.input is None else next(done) for u in units]


def _associate(
    m: Matching, u: Prepared, chk: Checked, trust: VehicleTrust
) -> tuple[np.ndarray, np.ndarray]:
    """The unit's checked association ``chk``: the landmark index of each ray (-1: none)
    and the rays to drop (of a track that went to a landmark without them). The vehicle's
    trust record takes the pass's gate result and offset, and may settle."""
    assert u.input is not None
    rays, cls, res = u.rays, u.input.cls, chk.res
    matched = chk.matched
    if chk.rejected:
        m.tally("group_rejected", chk.rejected)
    drop = np.zeros(len(rays), bool)
    if res.unlinked is not None and m.config.track_drop_unlinked:
        drop = res.unlinked & (matched < 0)
        m.tally("track_discarded", int(drop.sum()))
    n_hit = int((matched >= 0).sum())
    trust.add_gate(int(np.isin(rays.sign_class, cls).sum()), n_hit)
    if n_hit >= m.config.gate.min_offset_rays:
        raw = res.offset[:2] + u.applied  # the vehicle's own offset, before correction
        trust.add_offset(raw, res.offset_cov, m.config.trust.bias_sigma_m, u.pass_id)
    m.fleet.update(u.vehicle, trust)
    m.note_trust(u.vehicle, trust, m.fleet_ref())
    gone = settle(m, u.vehicle, trust)
    if gone:  # emptied by the settlement: these rays wait like unmatched ones
        out = np.array([c.id in gone for c in u.cands])
        matched = np.where((matched >= 0) & out[np.maximum(matched, 0)], -1, matched)
    return matched, drop


def match_unit(
    m: Matching, u: Prepared, at: float, received_at: float, res: Checked | None
) -> None:
    """Link the prepared unit's rays by its association ``res`` (None: computed here; see
    :func:`associate_prepared`), pool the rest, start landmarks, count sightings and note
    what it touched for the end of the tick. ``at`` is the unit's event time
    (:meth:`Matching.entry_time`): the vehicle is seen then, and a pooled ray waits from
    its own capture time (never later than ``at``); ``received_at`` (the ingest stamp)
    only traces latency."""
    tile, vehicle, pass_id, obs, cands = u.tile, u.vehicle, u.pass_id, u.obs, u.cands
    trust = m.state.seen(vehicle, at)
    if u.applied.any():
        m.tally("shift_corrected", len(obs))
    if u.track_invalid:
        m.tally("track_invalid", u.track_invalid)
    matched = np.full(len(u.rays), -1, np.int64)
    drop = np.zeros(len(u.rays), bool)
    if u.input is not None:
        if res is None:
            (res,) = associate_prepared(m, [u])
        assert res is not None
        matched, drop = _associate(m, u, res, trust)
    hit = matched >= 0
    m.tally("received", len(u.rays))
    m.tally("associated", int(hit.sum()))
    touched: set[int] = set()
    for i in np.flatnonzero(hit):
        touched.add(cands[matched[i]].id)
    linked = [cands[k] for k in matched[hit]]
    link(m, obs.take(hit), linked, vehicle, pass_id, received_at, (tile, u.rays.take(hit)))
    wait = ~hit & ~drop
    waiting = obs.take(wait)
    captured = np.asarray(waiting.t, float)
    since = np.where(np.isfinite(captured), np.minimum(captured, at), at)
    kept = np.hstack([u.rays.origin[wait], u.rays.direction[wait]])  # the pool's frame
    m.state.add_pending(tile, waiting, vehicle, pass_id, since, received_at, kept)
    born: set[int] = set()
    over = m.config.tick_s > 0 and over_budget(m, tile, vehicle, pass_id)
    cut = over and not quarantined(m, vehicle, pass_id)  # the tick ends after this unit
    if m.config.tick_s <= 0 or (over and not cut):  # (a quarantined pass: evicted only)
        new_classes = np.unique(obs.sign_class[wait])
        born = initiate(m, tile, u.area, vehicle, pass_id, new_classes)
        # after initiation took what it could: an honest upload's rays (all of them
        # waiting, in a tile with no landmark yet) are not evicted before they had their
        # chance
        enforce_budget(m, tile, vehicle, pass_id)
    elif not cut:  # tried with the tick's other uploads of the pass when the tick ends
        touch_budget(m, vehicle, pass_id)
    counted: list[int] = []
    if cands and m.config.sightings.enabled:
        # within a tick the candidates' gating estimates are the ones prepared; with
        # tick_s = 0 a settlement may have re-solved them in this unit
        arrays = u.input if m.config.tick_s > 0 else None
        counted = count_sightings(m, m.frames(tile), u.rays, cands, matched, arrays)
    m.state.note_tick(touched | born, counted)
    if m.config.tick_s <= 0:
        end_tick(m)
    elif cut:
        split_tick(m)
        # the tick's end tried every waiting ray (tile by tile, pass by pass key) and
        # enforced the budgets of the passes it tried; this one's record is touched here
        enforce_budget(m, tile, vehicle, pass_id)


def count_sightings(
    m: Matching,
    frame: Any,
    rays: LocalRays,
    cands: list[Landmark],
    matched: np.ndarray,
    arrays: UnitInput | None = None,
) -> list[int]:
    """Count, for the unit's candidate landmarks, whether it had them in view and whether
    it linked rays to them (:mod:`hdmap.mapping.sightings`; those not there are retired
    when the tick ends). ``rays`` are in ``frame`` (the unit's tile's); ``arrays``: the
    candidates' positions (in ``frame``) and facings as they still are, if known (else
    taken from ``cands``: the same values, a conversion being row-independent). Returns the
    ids counted."""
    cfg = m.config.sightings
    seen = np.zeros(len(cands), bool)
    seen[matched[matched >= 0]] = True
    view = seen.copy()
    rest = np.flatnonzero(~seen)  # a landmark the unit linked rays to is in view
    if rest.size:
        if arrays is not None and arrays.facing is not None:
            x, fac = arrays.x[rest], arrays.facing.take(rest)
        else:
            x = frame.from_ecef(np.array([cands[k].x for k in rest]))
            fac = gating_facings([cands[k] for k in rest])
        view[rest] = in_view(rays.origin, rays.direction, x, fac.azimuth, fac.known, cfg)
    counted: list[int] = []
    for k in np.flatnonzero(view):
        lm = cands[k]
        if m.state.landmarks.get(lm.id) is not lm:  # emptied in this unit
            continue
        lm.in_view += 1
        lm.seen += int(seen[k])
        m.state.put(lm)
        counted.append(lm.id)
    return counted


def group_check(
    m: Matching, rays: LocalRays, res: Association, x: np.ndarray, cov: np.ndarray
) -> np.ndarray:
    """``res.landmark`` without the groups whose rays meet elsewhere (see
    ``MatchingConfig.group_check``; counted ``group_rejected``)."""
    ((out, rejected),) = group_checks(m, [(rays, res, x, cov)])
    if rejected:
        m.tally("group_rejected", rejected)
    return out


def group_checks(
    m: Matching, units: list[tuple[LocalRays, Association, np.ndarray, np.ndarray]]
) -> list[tuple[np.ndarray, int]]:
    """:func:`group_check` of several units (rays, association, candidates' positions and
    covariances) at once, each as alone: its landmark indices and the rays it took out
    (not counted here). The groups' triangulations and tests run in one call; every
    group's sums are over its own rays in their order and each test is per group, so the
    result is the one each unit gets alone, to the bit."""
    outs = [res.landmark.copy() for _r, res, _x, _c in units]
    cfg = m.config
    if not cfg.group_check:
        return [(o, 0) for o in outs]
    moved: list[LocalRays] = []
    groups, lms_all, n_all, c_extra, d_ref = [], [], [], [], []
    base = 0
    for (rays, res, x, cov), out in zip(units, outs, strict=True):
        hit = np.flatnonzero(out >= 0)
        lms, grp, n = np.unique(out[hit], return_inverse=True, return_counts=True)
        moved.append(replace(rays.take(hit), origin=rays.origin[hit] + res.offset))
        groups.append(grp.astype(np.int64) + base)
        lms_all.append(lms)
        n_all.append(n)
        c_extra.append(cov[lms] + res.offset_cov)
        d_ref.append(x[lms])
        base += lms.size
    if base == 0:
        return [(o, 0) for o in outs]
    xt, ct = triangulate_groups(LocalRays.concat(moved), np.concatenate(groups), base)
    c = ct + np.concatenate(c_extra)
    d = xt - np.concatenate(d_ref)
    n = np.concatenate(n_all)
    test = (n >= cfg.group_min_rays) & np.isfinite(d).all(axis=1) & np.isfinite(c).all(axis=(1, 2))
    test &= np.abs(np.linalg.det(np.where(test[:, None, None], c, np.eye(3)))) > 1e-12
    chi2 = np.zeros(base)
    if test.any():
        chi2[test] = np.einsum(
            "ki,ki->k", d[test], np.linalg.solve(c[test], d[test][:, :, None])[:, :, 0]
        )
    bad = test & (chi2 > cfg.group_chi2)
    done: list[tuple[np.ndarray, int]] = []
    start = 0
    for out, lms in zip(outs, lms_all, strict=True):
        b = bad[start : start + lms.size]
        start += lms.size
        rejected = 0
        if b.any():
            drop = np.isin(out, lms[b])
            out[drop] = -1
            rejected = int(drop.sum())
        done.append((out, rejected))
    return done
