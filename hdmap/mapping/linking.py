"""Linking rays to landmarks in the matcher's gating sums, and the landmarks' gating
estimates.

:func:`link` queues a pass's rays for their landmarks' rows (with the vehicle's weight,
held apart while it is on probation; added in one call when the sums are next read,
:meth:`~hdmap.mapping.matching.Matching.flush_links`), notes their viewing directions and
co-visibility, and records the links in the home tiles' output; :func:`refresh`
re-solves the touched landmarks' gating estimates; :func:`create` makes a landmark with an
empty row.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

from hdmap.geo.geodesy import GEODESY
from hdmap.geo.tiles import quadkeys_of
from hdmap.mapping import box_ranges, presence
from hdmap.mapping.association import LocalRays
from hdmap.mapping.estimator import Rays
from hdmap.mapping.estimator.provisional import prior_covariance, usable
from hdmap.mapping.facing import summed_views
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.matching import Matching, facings_of
from schemas.ids import hold_key, pass_key


def to_local(frame: Any, obs: Any) -> LocalRays:
    """Observations (an :class:`~hdmap.mapping.landmarks.ObsRows` table) -> rays in a
    tile's ENU frame."""
    return local_rays(
        obs,
        frame.from_geodetic(obs.lat, obs.lon, obs.h),
        frame.vectors_from_enu_at(obs.direction, obs.lat, obs.lon),
    )


def local_rays(obs: Any, origin: np.ndarray, direction: np.ndarray) -> LocalRays:
    """:func:`to_local` of ``obs`` whose origins and directions in the frame are known."""
    return LocalRays(
        origin=origin,
        direction=direction,
        sigma_az=obs.sigma_az,
        sigma_el=obs.sigma_el,
        sigma_pos_h=obs.sigma_pos_h,
        sigma_pos_v=obs.sigma_pos_v,
        range_m=obs.range_m,
        sigma_range_m=obs.sigma_range_m,
        image=obs.image.astype(np.int64),
        sign_class=obs.sign_class.astype(np.int64),
        track=obs.track.astype(np.int64) if obs.track.any() else None,
    )


def to_rays(r: LocalRays, weight: np.ndarray | None = None) -> Rays:
    """Local rays as the estimator's input (``weight`` per ray; None: all 1)."""
    return Rays(
        r.origin,
        r.direction,
        r.sigma_az,
        r.sigma_el,
        r.sigma_pos_h,
        r.sigma_pos_v,
        weight,
        r.range_m,
        r.sigma_range_m,
    )


def link(
    m: Matching,
    obs: Any,
    lms: list[Landmark],
    vehicle: str,
    pass_id: int,
    received: float,
    local: tuple[str, LocalRays] | None = None,
) -> None:
    """Record associations (ray ``k`` of ``obs`` to ``lms[k]``): queued for the gating
    sums (:meth:`~hdmap.mapping.matching.Matching.flush_links`), output per home tile.
    ``local``: ``obs`` already in a tile's frame (:func:`to_local`, row for row), used for
    the landmarks of that home tile (the same conversion, not done twice)."""
    if not len(obs):
        return
    m.tally("linked", len(obs))
    t = m.state.trust_of(vehicle)
    weight = t.weight(m.config.trust, m.fleet_ref())
    if weight < 1.0:
        m.tally("downweighted", len(obs))
    held = t.held(m.config.trust)
    gating = weight
    if held:
        m.tally("held", len(obs))
        if m.config.gate_probation_full:
            gating = weight / m.config.trust.probation_weight
    key = pass_key(vehicle, pass_id, held)
    hold = np.full(len(obs), hold_key(vehicle) if held else 0, np.int64)
    note_views(m, obs, lms)
    by_home: dict[str, list[int]] = defaultdict(list)
    for k, lm in enumerate(lms):
        by_home[lm.home].append(k)
    for home, idx in sorted(by_home.items()):
        sel = np.array(idx)
        sub = obs.take(sel)
        if local is not None and local[0] == home:
            here = local[1].take(sel)
        else:
            here = to_local(m.frames(home), sub)
        rows = np.array([lms[k].row for k in idx], np.int64)
        rays = to_rays(here, np.full(len(idx), gating) if gating < 1.0 else None)
        _, first, inv = np.unique(rows, return_index=True, return_inverse=True)
        note_ranges(m, here, inv.reshape(-1), [lms[idx[f]] for f in first.tolist()])
        first_ids = [lms[idx[f]].id for f in first.tolist()]
        ids = np.array(first_ids, np.uint64)[inv.reshape(-1)]
        m.hold_link((rows, np.full(len(idx), key, np.int64), rays, hold[sel]), ids)
        m.state.mark_changed(first_ids)  # their rows' sums change
        before = m.quiet.members(key)
        m.quiet.note(key, list(zip(first_ids, rows[first].tolist(), strict=True)))
        fresh = [
            lms[idx[f]] for f, i in zip(first.tolist(), first_ids, strict=True) if i not in before
        ]
        presence.seen(m, vehicle, fresh, float(np.max(sub.t)))
        out = m.out[home]
        vi = out.vehicle_index(vehicle)
        out.links += [(lms[k].id, vi, pass_id) for k in idx]
        out.received_at += [received] * len(idx)
        out.weight += [weight] * len(idx)
        out.held += [held] * len(idx)
        if held:
            m.state.hold_home(vehicle, home)
        out.obs.append(sub)


def note_ranges(m: Matching, here: LocalRays, inv: np.ndarray, lms: list[Landmark]) -> None:
    """The rays' box ranges into their landmarks' range sums (``here``: the rays in the
    landmarks' home frame, ray ``k`` linked to ``lms[inv[k]]``)."""
    h, w = box_ranges.ray_terms(
        here.origin,
        here.direction,
        here.range_m,
        here.sigma_range_m,
        here.sigma_pos_h,
        m.config.estimator.panel_rel_sigma,
    )
    if not w.any():
        return
    sums = box_ranges.summed(inv, h, w)
    for lm, add in zip(lms, sums, strict=True):
        lm.ranges = lm.ranges + add


def note_views(m: Matching, obs: Any, lms: list[Landmark]) -> None:
    """Viewing directions, same-class landmarks linked together (co-passes: all rays here
    are of one vehicle pass) and detected in one image (co-visibility)."""
    first, view, _n = summed_views(np.array([lm.id for lm in lms], np.uint64), obs.direction)
    for j, k in enumerate(first.tolist()):
        lms[k].view = lms[k].view + view[j]
    if first.size < 2:
        return
    linked = sorted((lms[k].cls, lms[k].id) for k in first.tolist())
    for i, (ca, a) in enumerate(linked):
        for cb, b in linked[i + 1 :]:
            if ca != cb:
                break
            m.state.copass.add(a, b)
    img = obs.image.astype(np.int64)
    u, cnt = np.unique(img, return_counts=True)
    for im in u[cnt > 1].tolist():
        here = np.flatnonzero(img == im)
        both = sorted({(lms[k].cls, lms[k].id) for k in here.tolist()})
        for i, (ca, a) in enumerate(both):
            for cb, b in both[i + 1 :]:
                if ca == cb:
                    m.state.add_covis(a, b)


def create(m: Matching, home: str, cls: int, x_ecef: np.ndarray, cov: np.ndarray) -> Landmark:
    """A new landmark of class ``cls`` at ``x_ecef`` with home tile ``home``: an empty sums
    row, and the triangulation's covariance ``cov`` plus the pass-bias prior to gate with."""
    lid = m.state.next_id(home)
    frame = m.frames(home)
    row = int(m.new_rows(1, frame.from_ecef(x_ecef[None]))[0])
    bias = m.config.gate.pass_bias_sigma_m
    gate_cov = cov + np.diag([bias**2, bias**2, m.config.gate.vertical_bias_sigma_m**2])
    lm = Landmark(lid, cls, home, m.tile_of(x_ecef), x_ecef, gate_cov, row, m.now)
    m.state.put(lm)
    return lm


def refresh(m: Matching, ids: list[int]) -> None:
    """Re-solve touched landmarks' gating estimates and facings (vectorised over them)."""
    if not ids:
        return
    m.state.gating_version += 1
    lms = [m.state.landmarks[i] for i in ids]
    sol = m.sums.solve(np.array([lm.row for lm in lms], np.int64), update_reference=False)
    g = m.config.gate
    bias = (g.pass_bias_sigma_m, g.pass_bias_sigma_m, g.vertical_bias_sigma_m)
    good, _prov, cov = usable(sol, m.config.estimator, m.config.provisional_passes, bias)
    if m.config.gate_bias_floor:
        cov = cov + prior_covariance(bias, sol.n_clusters)
    moved = [k for k in range(len(lms)) if good[k]]
    by_home: dict[str, list[int]] = defaultdict(list)
    for k in moved:
        by_home[lms[k].home].append(k)
    for home, ks in by_home.items():  # one conversion per frame (element-wise: the same)
        for k, x in zip(ks, m.frames(home).to_ecef(sol.x[ks]), strict=True):
            lms[k].x = x
            lms[k].cov = cov[k]
    if moved:
        lat, lon, _ = GEODESY.to_geodetic(np.array([lms[k].x for k in moved]))
        for k, t in zip(moved, quadkeys_of(lat, lon, m.zoom).tolist(), strict=True):
            lms[k].tile = str(t)
    scales = panel_scales(m, lms)
    for lm, fk, sk in zip(lms, facings_of(m, lms).rows(), scales.tolist(), strict=True):
        lm.facing = fk
        lm.scale = sk
        m.state.put(lm)


def panel_scales(m: Matching, lms: list[Landmark]) -> np.ndarray:
    """Each landmark's panel scale at its gating position (``Landmark.scale``): its rays'
    mean relative range there, NaN with fewer than ``gate.scale_min_passes`` passes."""
    out = np.full(len(lms), np.nan)
    if m.config.gate.landmark_scale == "off" or not lms:
        return out
    passes = m.sums.n_passes(np.array([lm.row for lm in lms], np.int64))
    by_home: dict[str, list[int]] = defaultdict(list)
    for k, lm in enumerate(lms):
        if passes[k] >= m.config.gate.scale_min_passes:
            by_home[lm.home].append(k)
    for home, ks in by_home.items():
        x = m.frames(home).from_ecef(np.array([lms[k].x for k in ks])).reshape(-1, 3)
        sums = np.array([lms[k].ranges for k in ks])
        out[ks] = box_ranges.mean_relative_range(sums, x)
    return out


def refresh_due(m: Matching, ids: list[int]) -> None:
    """Re-solve ``ids`` now with ``tick_s = 0``, else when the gating tick ends
    (:mod:`hdmap.mapping.tick`)."""
    if m.config.tick_s > 0:
        m.state.note_tick(set(ids), [])
    else:
        refresh(m, ids)
