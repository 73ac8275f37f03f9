"""Matcher: the single writer of landmark identities for its region.

Per obs entry (one upload's rays for one tile, in order; see :mod:`hdmap.runtime.stage`):

1. rays into the tile's ENU frame; candidate landmarks of the same classes from
   the tile and its 8 neighbours (so a sign near a border is one landmark);
2. :func:`hdmap.mapping.association.associate`: gate, per-pass offset, per-image assignment;
3. unmatched rays join the pending pool; the pass's pending rays (this tile and
   its neighbours) may form candidate landmarks (:mod:`hdmap.mapping.initiation`); then
   pending rays of other passes are offered to the new landmarks;
4. matched rays update the matcher's own gating sums (the same estimator as the
   solver, so gating is deterministic given the input order), and one
   :class:`schemas.AssocGroup` per landmark home tile goes to the assoc log;
5. merge: a touched landmark and another of its class whose estimates agree (chi-square
   of the difference under both covariances), that are seen from the same side and were
   seldom detected in one image together (``merge_max_covis``), are one sign: the younger one's sums
   fold into the other's (:meth:`LandmarkSums.merge_rows`) and it is retired with
   ``merged_into`` in the assoc log, so the solver does the same and the publisher
   removes it.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field, replace

import numpy as np

from hdmap.geo.geodesy import GEODESY
from hdmap.geo.tiles import TileFrames, frame_map, in_region, neighbours, quadkeys_of
from hdmap.mapping.association import (
    Association,
    GateConfig,
    LocalRays,
    associate,
    origin_cov,
    pair_chi2,
    valid_tracks,
)
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from hdmap.mapping.estimator.provisional import prior_covariance, usable
from hdmap.mapping.initiation import InitConfig, propose, triangulate_groups
from hdmap.mapping.quiet import QuietPasses, close_quiet, merge_rows, note_open
from hdmap.mapping.trust import CAUGHT, FleetOffsets, TrustConfig, VehicleTrust
from hdmap.runtime.config import ConfigError
from hdmap.runtime.stage import StageService
from schemas import (
    DROP,
    RELEASE,
    AssocGroup,
    DecodeError,
    Links,
    LogEntry,
    NewLandmarks,
    Observations,
    ObsGroup,
    TrustChanges,
)
from schemas.ids import hold_key, pass_key
from services.matcher.state import Landmark, MatcherState

log = logging.getLogger(__name__)


def gating_estimator() -> EstimatorConfig:
    """The matcher's estimator: the solver's, with the plug-in meat
    (``integrated_meat`` off). The gate and merge thresholds were measured with it; the
    integrated meat widens young landmarks' gates, and on the four-seed fleet evaluation
    that turned 0/0/0/0 duplicated landmarks into 0/0/2/0 and moved coverage from 30 passes
    from 0.969 to 0.981 on seed 3 (docs/estimator.md section 6)."""
    return EstimatorConfig(integrated_meat=False)


@dataclass(frozen=True)
class MatcherConfig:
    gate: GateConfig = field(default_factory=GateConfig)
    init: InitConfig = field(default_factory=InitConfig)
    estimator: EstimatorConfig = field(default_factory=gating_estimator)
    gate_probation_full: bool = True
    """Rays of a vehicle on probation count in full in the matcher's own (gating) sums; the
    solver's, which make the map, get the probation weight."""
    pending_ttl_s: float = 3600.0
    """Unmatched rays older than this are dropped (counted as expired)."""
    close_passes_after_s: float = 7200.0
    """Close a pass in the gating sums once no ray of it has been linked for this long
    (wall-clock seconds, :mod:`hdmap.mapping.quiet`; 0: open until evicted). Above
    ``pending_ttl_s``: a pending ray can still be linked until it expires."""
    trust: TrustConfig = field(default_factory=TrustConfig)
    """Per-vehicle weights from the history of its pass offsets and gate failures."""
    gate_bias_floor: bool = True
    """Gate with the solution's covariance plus the pass-bias prior over its passes
    (``diag(bias^2) / G``): the between-pass covariance of a few passes is itself noisy,
    and a gate that is too tight splits one sign into several landmarks."""
    group_check: bool = True
    """The rays of one unit given to one landmark must meet near it: their own
    triangulation (origins moved by the unit's offset) against the landmark, chi-square
    (3 dof) under both covariances and the offset's. Rays of a neighbouring sign of the
    class pass the per-ray gate one by one, but they meet at their own sign."""
    group_chi2: float = 16.27
    group_min_rays: int = 2
    track_drop_unlinked: bool = True
    """Rays of a track that went to a landmark without them (outside the gate) are dropped
    rather than left to start another landmark of the same sign."""
    merge: bool = True
    """Merge landmarks found to be one sign (step 5 of the module doc)."""
    merge_chi2: float = 16.27
    """Largest chi-square (3 dof; 16.27 = 99.9 %) of the difference of two estimates, under
    the sum of their gating covariances."""
    merge_max_m: float = 10.0
    """Largest horizontal distance between two landmarks that may merge."""
    merge_max_covis: float = 0.2
    """Largest share of the smaller landmark's rays in images that also detected the other.
    Two signs seen from the same roads are detected together in most images where both are
    in view (0.33-0.79 over the fleet evaluation's four seeds); two landmarks of one sign
    are detected together only through the other signs' rays one of them took by mistake
    (0.11-0.28). 0.1 until 2026-11-30: it kept such duplicates apart (seed 0's sign 130:
    two landmarks 0.1 m apart, 0.13)."""
    merge_min_view_cos: float = 0.5
    """Smallest cosine between the two landmarks' mean viewing directions."""
    merge_min_passes: int = 2
    """Both landmarks need this many passes (a one-pass estimate carries its pass's whole
    bias). 5 before onboard tracks; with them co-visibility tells two signs apart reliably
    and 2 cut the young map's duplicates at 3-4 passes from 13-48 to 0-5 (four seeds, with
    ``merge_max_covis`` 0.1; with 0.2: 2 / 0 / 9 / 3).
    A landmark looks for a partner at each of its passes up to twice this, then at every
    third (the search is most of a unit's cost otherwise)."""
    provisional_passes: int = 0
    """If > 0, gating estimates follow the landmark's solution from this many passes on
    (before the estimator's ``min_clusters``, with the pass-bias prior in the covariance;
    see :mod:`hdmap.mapping.estimator.provisional`). Off: until ``min_clusters`` passes the gate
    uses the initiating pass's triangulation with the full pass bias, which the fleet
    evaluation found far safer (with 2: association right 0.51 vs 0.81 at 20-29 passes,
    many more duplicates; a 2-4 pass sandwich covariance is too small to gate with)."""

    def __post_init__(self) -> None:
        if 0 < self.close_passes_after_s <= self.pending_ttl_s:
            raise ConfigError(
                "matcher.close_passes_after_s: must exceed pending_ttl_s "
                f"({self.pending_ttl_s}), got {self.close_passes_after_s} (a pending ray of a "
                "closed pass would start a new cluster); 0 keeps passes open"
            )


def shift_origins(frame, obs: Observations, d_en: np.ndarray) -> Observations:
    """The same observations with origins moved by ``d_en`` (East, North metres)."""
    x = frame.from_geodetic(obs.lat, obs.lon, obs.h)
    x[:, :2] += np.asarray(d_en, float)[:2]
    lat, lon, h = frame.to_geodetic(x)
    return replace(obs, lat=lat, lon=lon, h=h)


def to_local(frame, obs: Observations) -> LocalRays:
    """Wire observations -> rays in a tile's ENU frame."""
    return LocalRays(
        origin=frame.from_geodetic(obs.lat, obs.lon, obs.h),
        direction=frame.vectors_from_enu_at(obs.direction, obs.lat, obs.lon),
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
    return Rays(r.origin, r.direction, r.sigma_az, r.sigma_el, r.sigma_pos_h, r.sigma_pos_v, weight)


@dataclass
class _Out:
    """Assoc output being built for one home tile during one apply."""

    vehicles: list[str] = field(default_factory=list)
    links: list[tuple[int, int, int]] = field(default_factory=list)
    received_at: list[float] = field(default_factory=list)
    weight: list[float] = field(default_factory=list)
    held: list[bool] = field(default_factory=list)
    obs: list[Observations] = field(default_factory=list)
    trust: list[tuple[int, int, float]] = field(default_factory=list)
    """(vehicle index, action, weight): vehicles leaving probation."""
    created: list[tuple[int, int, float, float, float]] = field(default_factory=list)
    retired: list[tuple[int, int]] = field(default_factory=list)
    """(retired id, id it merged into)."""
    ended: list[int] = field(default_factory=list)
    """Retired without a successor (emptied: every ray taken out)."""

    def vehicle_index(self, v: str) -> int:
        if v not in self.vehicles:
            self.vehicles.append(v)
        return self.vehicles.index(v)


class MatcherService(StageService):
    name = "matcher"
    input_stage = "obs"
    upstream = "ingest"
    output_stage = "assoc"

    def __init__(self, opts, config: MatcherConfig | None = None):
        super().__init__(opts)
        self.config = config or MatcherConfig()
        self.frames = TileFrames()
        self._areas: dict[str, list[str]] = {}
        self.sums = LandmarkSums(self.config.estimator)
        self.state = MatcherState(self.db)
        self._quiet = QuietPasses(self.config.close_passes_after_s)
        self._reload()
        self._out: dict[str, _Out] = {}
        self._counts: dict[str, float] = {}
        self._snapshot_counts()

    # -- transaction participants: on failure, memory is rebuilt from the database --------

    def _reload(self) -> None:
        self.sums = LandmarkSums(self.config.estimator)
        self.state.load(self.sums.unpack_rows)
        self._quiet.clear()
        note_open(self._quiet, self.sums, self.state)
        self._flagged: dict[str, tuple[float, float]] = {}
        self._fleet = FleetOffsets(self.config.trust)
        for v, t in sorted(self.state.trust.items()):
            self._fleet.update(v, t)
        ref = self._fleet_ref()
        for v, t in self.state.trust.items():
            self._note_trust(v, t, ref)

    def _note_trust(self, vehicle: str, t: VehicleTrust, ref: np.ndarray | None) -> None:
        """Keep (weight, offset chi2) of the vehicles stats show: downweighted or suspect."""
        w, c = t.weight(self.config.trust, ref), t.chi2(ref)
        if w < 1.0 or c > self.config.trust.chi2_gate:
            self._flagged[vehicle] = (w, c)
        else:
            self._flagged.pop(vehicle, None)

    def _area(self, tile: str) -> list[str]:
        """``tile`` and its 8 neighbours (cached: mercantile costs ~0.1 ms a call)."""
        a = self._areas.get(tile)
        if a is None:
            a = self._areas[tile] = [tile, *neighbours(tile)]
        return a

    def _fleet_ref(self) -> np.ndarray | None:
        """The fleet's reference offset for the trust test (None while trust is off)."""
        if not self.config.trust.enabled:
            return None
        return self._fleet.reference()

    def on_commit(self) -> None:
        pass

    def on_rollback(self) -> None:
        self._reload()

    def participants(self) -> list:
        return [self]

    def setup(self) -> None:
        super().setup()
        self.every(60.0, lambda _now: self.expire())

    # -- apply -----------------------------------------------------------------------------

    def apply(self, entries: list[LogEntry]) -> None:
        self._out = defaultdict(_Out)
        now = 0.0
        for e in entries:
            try:
                group = ObsGroup.from_bytes(e.body)
            except DecodeError as exc:
                self.reject(f"obs.{exc.field}")
                continue
            self._unit(e.tile, group)
            now = max(now, group.received_at)
        self._freeze_stale(now)
        for home, out in sorted(self._out.items()):
            self.emit(home, self._assoc_body(out))
        self.count("passes_closed", close_quiet(self._quiet, self.sums, self.state))
        self.state.save(self.sums.pack_rows)

    def _unit(self, tile: str, g: ObsGroup) -> None:
        frame = self.frames(tile)
        trust = self.state.trust_of(g.vehicle_id)
        trust.last_seen = max(trust.last_seen, g.received_at)
        obs = g.obs
        applied = np.zeros(2)
        ref = self._fleet_ref()
        if trust.suspect(self.config.trust, ref):
            applied = trust.mean_offset(ref)
            obs = shift_origins(frame, obs, applied)
            self.count("shift_corrected", len(obs))
        if obs.track.any():  # the vehicle's labels are checked once, as they come in
            track = valid_tracks(obs.track, obs.image).astype(np.uint32)
            self.count("track_invalid", int((obs.track != track).sum()))
            obs = replace(obs, track=track)
        rays = to_local(frame, obs)
        area = self._area(tile)
        cands = self.state.near(area)
        matched = np.full(len(rays), -1, np.int64)
        drop = np.zeros(len(rays), bool)
        if cands:
            x = frame.from_ecef(np.array([c.x for c in cands]))
            cov = np.array([c.cov for c in cands])
            cls = np.array([c.cls for c in cands], np.int64)
            res: Association = associate(rays, x, cov, cls, self.config.gate)
            matched = self._group_check(rays, res, x, cov)
            if res.unlinked is not None and self.config.track_drop_unlinked:
                drop = res.unlinked & (matched < 0)
                self.count("track_discarded", int(drop.sum()))
            n_hit = int((matched >= 0).sum())
            trust.add_gate(int(np.isin(rays.sign_class, cls).sum()), n_hit)
            if n_hit >= self.config.gate.min_offset_rays:
                raw = res.offset[:2] + applied  # the vehicle's own offset, before correction
                trust.add_offset(raw, res.offset_cov, self.config.trust.bias_sigma_m, g.pass_id)
            self._fleet.update(g.vehicle_id, trust)
            self._note_trust(g.vehicle_id, trust, self._fleet_ref())
            gone = self._settle(g.vehicle_id, trust)
            if gone:  # emptied by the settlement: these rays wait like unmatched ones
                out = np.array([c.id in gone for c in cands])
                matched = np.where((matched >= 0) & out[np.maximum(matched, 0)], -1, matched)
        hit = matched >= 0
        self.count("received", len(rays))
        self.count("associated", int(hit.sum()))
        touched: set[int] = set()
        for i in np.flatnonzero(hit):
            touched.add(cands[matched[i]].id)
        self._link(
            obs.take(hit),
            [cands[k] for k in matched[hit]],
            g.vehicle_id,
            g.pass_id,
            g.received_at,
        )
        wait = ~hit & ~drop
        self.state.add_pending(
            tile, obs.take(wait), g.vehicle_id, g.pass_id, time.time(), g.received_at
        )
        new_classes = np.unique(obs.sign_class[wait])
        touched |= self._initiate(tile, area, g.vehicle_id, g.pass_id, new_classes)
        self._refresh(sorted(touched))
        self._merge_touched(sorted(touched))

    def _group_check(
        self, rays: LocalRays, res: Association, x: np.ndarray, cov: np.ndarray
    ) -> np.ndarray:
        """``res.landmark`` without the groups whose rays meet elsewhere (see config)."""
        out = res.landmark.copy()
        cfg = self.config
        if not cfg.group_check:
            return out
        hit = np.flatnonzero(out >= 0)
        if hit.size == 0:
            return out
        lms, grp, n = np.unique(out[hit], return_inverse=True, return_counts=True)
        moved = replace(rays.take(hit), origin=rays.origin[hit] + res.offset)
        xt, ct = triangulate_groups(moved, grp, lms.size)
        c = ct + cov[lms] + res.offset_cov
        d = xt - x[lms]
        test = (
            (n >= cfg.group_min_rays) & np.isfinite(d).all(axis=1) & np.isfinite(c).all(axis=(1, 2))
        )
        test &= np.abs(np.linalg.det(np.where(test[:, None, None], c, np.eye(3)))) > 1e-12
        chi2 = np.zeros(lms.size)
        if test.any():
            chi2[test] = np.einsum(
                "ki,ki->k", d[test], np.linalg.solve(c[test], d[test][:, :, None])[:, :, 0]
            )
        bad = test & (chi2 > cfg.group_chi2)
        if bad.any():
            drop = np.isin(out, lms[bad])
            out[drop] = -1
            self.count("group_rejected", int(drop.sum()))
        return out

    def _link(
        self, obs: Observations, lms: list[Landmark], vehicle: str, pass_id: int, received: float
    ) -> None:
        """Record associations: gating sums now, assoc output per home tile."""
        if not len(obs):
            return
        self.count("linked", len(obs))
        t = self.state.trust_of(vehicle)
        weight = t.weight(self.config.trust, self._fleet_ref())
        if weight < 1.0:
            self.count("downweighted", len(obs))
        held = t.held(self.config.trust)
        gating = weight
        if held:
            self.count("held", len(obs))
            if self.config.gate_probation_full:
                gating = weight / self.config.trust.probation_weight
        key = pass_key(vehicle, pass_id, held)
        hold = np.full(len(obs), hold_key(vehicle) if held else 0, np.int64)
        self._note_views(obs, lms)
        by_home: dict[str, list[int]] = defaultdict(list)
        for k, lm in enumerate(lms):
            by_home[lm.home].append(k)
        for home, idx in sorted(by_home.items()):
            sel = np.array(idx)
            sub = obs.take(sel)
            local = to_local(self.frames(home), sub)
            rows = np.array([lms[k].row for k in idx], np.int64)
            rays = to_rays(local, np.full(len(idx), gating) if gating < 1.0 else None)
            self.sums.accumulate(rows, np.full(len(idx), key, np.int64), rays, hold[sel])
            _, first = np.unique(rows, return_index=True)
            self._quiet.note(key, [(lms[idx[f]].id, lms[idx[f]].row) for f in first])
            out = self._out[home]
            vi = out.vehicle_index(vehicle)
            out.links += [(lms[k].id, vi, pass_id) for k in idx]
            out.received_at += [received] * len(idx)
            out.weight += [weight] * len(idx)
            out.held += [held] * len(idx)
            if held:
                t.held_homes.add(home)
            out.obs.append(sub)

    def _note_views(self, obs: Observations, lms: list[Landmark]) -> None:
        """Viewing directions, and same-class landmarks detected in one image (all rays
        here are of one vehicle pass)."""
        ids = np.array([lm.id for lm in lms], np.uint64)
        uniq, first, inv = np.unique(ids, return_index=True, return_inverse=True)
        d = obs.direction[:, :2]
        n = np.linalg.norm(d, axis=1, keepdims=True)
        view = np.zeros((uniq.size, 2))
        np.add.at(view, inv, np.divide(d, n, out=np.zeros_like(d), where=n > 0))
        for j, k in enumerate(first.tolist()):
            lms[k].view = lms[k].view + view[j]
        if uniq.size < 2:
            return
        img = obs.image.astype(np.int64)
        u, cnt = np.unique(img, return_counts=True)
        for m in u[cnt > 1].tolist():
            here = np.flatnonzero(img == m)
            both = sorted({(lms[k].cls, lms[k].id) for k in here.tolist()})
            for i, (ca, a) in enumerate(both):
                for cb, b in both[i + 1 :]:
                    if ca == cb:
                        self.state.add_covis(a, b)

    def _initiate(
        self, tile: str, area: list[str], vehicle: str, pass_id: int, classes: np.ndarray
    ) -> set[int]:
        """Candidate landmarks from this pass's pending rays around ``tile``, for the classes
        that just got new pending rays (for the others, this pass's pending rays only
        shrank since they last failed to make a landmark)."""
        if classes.size == 0:
            return set()
        frame = self.frames(tile)
        key = pass_key(vehicle, pass_id)
        where: list[tuple[str, np.ndarray]] = []  # (tile, rows of its pending pool)
        for t in area:
            p = self.state.pending.get(t)
            if p is not None and (mine := np.flatnonzero(p.key == key)).size:
                where.append((t, mine))
        if not where:
            return set()
        obs = Observations.concat([self.state.pending[t].obs.take(i) for t, i in where])
        received = max(float(self.state.pending[t].received_at[i].max()) for t, i in where)
        rays = to_local(frame, obs)
        created: set[int] = set()
        used = np.zeros(len(rays), bool)
        for cls in np.intersect1d(np.unique(rays.sign_class), classes):
            idx = np.flatnonzero(rays.sign_class == cls)
            for cand in propose(rays.take(idx), self.config.gate, self.config.init):
                members = idx[cand.members]
                lat, lon, h = frame.to_geodetic(cand.x[None])
                home_tile = str(quadkeys_of(lat, lon, self.opts.zoom)[0])
                if not in_region(home_tile, self.region):
                    home_tile = tile
                lm = self._create(home_tile, int(cls), frame.to_ecef(cand.x[None])[0], cand.cov)
                out = self._out[lm.home]
                out.created.append((lm.id, int(cls), float(lat[0]), float(lon[0]), float(h[0])))
                self._link(obs.take(members), [lm] * len(members), vehicle, pass_id, received)
                used[members] = True
                created.add(lm.id)
        self._drop_used(where, used)
        if created:
            self.count("created", len(created))
            self._adopt(area, [self.state.landmarks[i] for i in sorted(created)])
        return created

    def _settle(self, vehicle: str, t: VehicleTrust) -> set[int]:
        """A vehicle leaves probation: its held passes count in full (promoted) or go
        (caught), here and, through the assoc output of every home tile it has held passes
        in, in the solvers. Returns the landmarks that went with them."""
        ref = self._fleet_ref()
        status = t.settle(self.config.trust, ref)
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
            self.count("vehicles_caught")
            return self._let_go(vehicle, t, DROP, 0.0)
        self.count("vehicles_promoted")
        return self._let_go(vehicle, t, RELEASE, t.weight(self.config.trust, ref))

    def _freeze_stale(self, now: float) -> None:
        """Vehicles on probation that stopped driving before they could be settled (none for
        ``probation_ttl_s`` of ingest time): their held passes go at the probation weight."""
        cfg = self.config.trust
        cutoff = now - cfg.probation_ttl_s
        for v in sorted(v for v, t in self.state.trust.items() if t.held_homes):
            t = self.state.trust[v]
            if t.held(cfg) and t.last_seen < cutoff:
                self.state.trust_of(v)  # marks it for saving
                w = t.weight(cfg, self._fleet_ref())
                local = w / cfg.probation_weight if self.config.gate_probation_full else w
                self._let_go(v, t, RELEASE, w, local)
                self.count("probation_timed_out")

    def _let_go(
        self, vehicle: str, t: VehicleTrust, action: int, weight: float, local: float | None = None
    ) -> set[int]:
        """Settle ``vehicle``'s held passes here (released at ``local``, default ``weight``)
        and, through the assoc output of every home tile it has held passes in, in the
        solvers (released at ``weight``). Returns the landmarks retired for having no rays
        left."""
        key = hold_key(vehicle)
        if action == DROP:
            rows = self.sums.drop_held(key)
        else:
            rows = self.sums.release(key, weight if local is None else local)
        for home in sorted(t.held_homes):
            out = self._out[home]
            out.trust.append((out.vehicle_index(vehicle), action, weight))
        t.held_homes.clear()
        if not rows.size:
            return set()
        by_row = {lm.row: lm for lm in self.state.landmarks.values()}
        lms = [by_row[r] for r in rows.tolist() if r in by_row]
        empty = self.sums.n_obs([lm.row for lm in lms]) == 0
        gone = {lm.id for lm, e in zip(lms, empty, strict=True) if e}
        for lm in lms:
            if lm.id in gone:
                self.state.remove(lm)  # only the caught vehicle saw it
                self._out[lm.home].ended.append(lm.id)
                self.count("emptied")
        self._refresh(sorted(lm.id for lm in lms if lm.id not in gone))
        return gone

    def _create(self, home: str, cls: int, x_ecef: np.ndarray, cov: np.ndarray) -> Landmark:
        lid = self.state.next_id(home)
        frame = self.frames(home)
        row = int(self.sums.new_rows(1, frame.from_ecef(x_ecef[None]))[0])
        bias = self.config.gate.pass_bias_sigma_m
        gate_cov = cov + np.diag([bias**2, bias**2, self.config.gate.vertical_bias_sigma_m**2])
        lm = Landmark(lid, cls, home, self._tile_of(x_ecef), x_ecef, gate_cov, row, time.time())
        self.state.put(lm)
        return lm

    def _adopt(self, area: list[str], new: list[Landmark]) -> None:
        """Offer pending rays of other passes to freshly created landmarks."""
        for t in area:
            p = self.state.pending.get(t)
            if p is None or not len(p):
                continue
            frame = self.frames(t)
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
            g = self.config.gate
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
                res = associate(local.take(js), x, cov, cls, self.config.gate)
                hit = res.landmark >= 0
                if hit.any():
                    take[sel[hit]] = True
                    rec = float(p.received_at[sel[hit]].max())
                    links.append((sel[hit], res.landmark[hit], v, pid, rec))
            for sel, lmi, v, pid, rec in links:
                self._link(p.obs.take(sel), [new[k] for k in lmi], v, pid, rec)
                self.count("adopted", len(sel))
            self.state.drop_pending(t, take)

    def _drop_used(self, where: list[tuple[str, np.ndarray]], used: np.ndarray) -> None:
        """Remove from each tile's pool the rows ``used`` marks (``used`` follows ``where``)."""
        start = 0
        for t, rows in where:
            u = used[start : start + rows.size]
            start += rows.size
            if u.any():
                mask = np.zeros(len(self.state.pending[t]), bool)
                mask[rows[u]] = True
                self.state.drop_pending(t, mask)

    def _refresh(self, ids: list[int]) -> None:
        """Re-solve touched landmarks' gating estimates (vectorised over them)."""
        if not ids:
            return
        lms = [self.state.landmarks[i] for i in ids]
        sol = self.sums.solve(np.array([lm.row for lm in lms], np.int64), update_reference=False)
        g = self.config.gate
        bias = (g.pass_bias_sigma_m, g.pass_bias_sigma_m, g.vertical_bias_sigma_m)
        good, _prov, cov = usable(sol, self.config.estimator, self.config.provisional_passes, bias)
        if self.config.gate_bias_floor:
            cov = cov + prior_covariance(bias, sol.n_clusters)
        moved = [k for k in range(len(lms)) if good[k]]
        for k in moved:
            lms[k].x = self.frames(lms[k].home).to_ecef(sol.x[k][None])[0]
            lms[k].cov = cov[k]
        if moved:
            lat, lon, _ = GEODESY.to_geodetic(np.array([lms[k].x for k in moved]))
            for k, t in zip(moved, quadkeys_of(lat, lon, self.opts.zoom).tolist(), strict=True):
                lms[k].tile = str(t)
        for lm in lms:
            self.state.put(lm)

    # -- merge --------------------------------------------------------------------------------

    def _merge_touched(self, ids: list[int]) -> None:
        if not self.config.merge:
            return
        for lid in ids:
            lm = self.state.landmarks.get(lid)
            if lm is None:  # merged away a moment ago
                continue
            other = self._merge_partner(lm)
            if other is None:
                continue
            n = self.sums.n_obs([lm.row, other.row])
            keep, drop = (lm, other) if (-n[0], lm.id) < (-n[1], other.id) else (other, lm)
            self._merge(keep, drop)

    def _merge_partner(self, lm: Landmark) -> Landmark | None:
        """The same-class landmark ``lm`` is one sign with (best chi-square), if any."""
        cfg = self.config
        g = int(self.sums.n_passes([lm.row])[0])
        if g < cfg.merge_min_passes or (g > 2 * cfg.merge_min_passes and g % 3):
            return None  # checked at every pass while young, then at every third
        cands = [
            c for c in self.state.near(self._area(lm.tile)) if c.cls == lm.cls and c.id != lm.id
        ]
        if cands and cfg.merge_min_passes > 0:
            n = self.sums.n_passes([c.row for c in cands])
            cands = [c for c, k in zip(cands, n, strict=True) if k >= cfg.merge_min_passes]
        if not cands:
            return None
        # ENU differences: the frame's rotation of ECEF differences (no projection needed)
        d = (np.array([c.x for c in cands]) - lm.x) @ self.frames(lm.home).rotation.T
        c = lm.cov[None] + np.array([c.cov for c in cands])
        chi2 = np.einsum("ki,ki->k", d, np.linalg.solve(c, d[:, :, None])[:, :, 0])
        near = (chi2 <= cfg.merge_chi2) & (np.hypot(d[:, 0], d[:, 1]) <= cfg.merge_max_m)
        for k in np.argsort(chi2, kind="stable").tolist():
            if not near[k]:
                break
            o = cands[k]
            n = self.sums.n_obs([lm.row, o.row])
            if self.state.covis_count(lm.id, o.id) > cfg.merge_max_covis * max(n.min(), 1):
                continue
            va, vb = lm.view, o.view
            norm = float(np.linalg.norm(va) * np.linalg.norm(vb))
            if norm > 0 and float(va @ vb) < cfg.merge_min_view_cos * norm:
                continue
            return o
        return None

    def _merge(self, keep: Landmark, drop: Landmark) -> None:
        rot, t = frame_map(self.frames(drop.home), self.frames(keep.home))
        merge_rows(self._quiet, self.sums, keep, drop, rot, t)
        self.state.merge(keep, drop)
        self._out[drop.home].retired.append((drop.id, keep.id))
        self.count("merged")
        self._refresh([keep.id])

    def _tile_of(self, x_ecef: np.ndarray) -> str:
        lat, lon, _ = GEODESY.to_geodetic(x_ecef[None])
        return str(quadkeys_of(lat, lon, self.opts.zoom)[0])

    def _assoc_body(self, out: _Out) -> bytes:
        links = np.array(out.links, dtype=np.uint64).reshape(-1, 3)
        created = out.created
        retired = np.array(out.retired, np.uint64).reshape(-1, 2)
        return AssocGroup(
            vehicles=out.vehicles,
            links=Links(
                links[:, 0],
                links[:, 1].astype(np.uint32),
                links[:, 2],
                np.array(out.received_at, float),
                np.array(out.weight, np.float32),
            ),
            obs=Observations.concat(out.obs),
            created=NewLandmarks(
                id=np.array([c[0] for c in created], np.uint64),
                sign_class=np.array([c[1] for c in created], np.uint16),
                lat=np.array([c[2] for c in created], float),
                lon=np.array([c[3] for c in created], float),
                h=np.array([c[4] for c in created], float),
            ),
            retired=np.r_[retired[:, 0], np.array(out.ended, np.uint64)],
            merged_into=retired[:, 1].copy(),
            held=np.array(out.held, bool),
            trust=TrustChanges(
                np.array([c[0] for c in out.trust], np.uint32),
                np.array([c[1] for c in out.trust], np.uint8),
                np.array([c[2] for c in out.trust], np.float32),
            ),
        ).to_bytes()

    # -- timers and stats -----------------------------------------------------------------------

    def expire(self) -> None:
        cutoff = time.time() - self.config.pending_ttl_s
        n = 0
        for t, p in list(self.state.pending.items()):
            old = p.added_at < cutoff
            if old.any():
                self.state.drop_pending(t, old)
                n += int(old.sum())
        if n:
            with self.transaction([self]):
                self.state.save(self.sums.pack_rows)
                self.count("expired", n)
        self._snapshot_counts()

    def after_commit(self) -> None:
        self._snapshot_counts()

    def _snapshot_counts(self) -> None:
        """Counts for the stats thread, taken on the worker thread."""
        self._counts = {
            "landmarks": len(self.state.landmarks),
            "pending": self.state.pending_count(),
        }
        low = sorted((w, v) for v, (w, _c) in self._flagged.items() if w < 1.0)
        self._counts["vehicles_downweighted"] = len(low)
        for w, v in low[:20]:  # the 20 least trusted, by name
            self._counts[f"weight.{v}"] = round(w, 6)
        gate = self.config.trust.chi2_gate
        odd = sorted((c, v) for v, (_w, c) in self._flagged.items() if c > gate)
        for c, v in odd[-5:]:  # the 5 most consistent offsets (whether or not trust is on)
            self._counts[f"offset_chi2.{v}"] = round(c, 2)

    def extra_counters(self) -> dict[str, float]:
        out = super().extra_counters()
        out.update(self._counts)
        return out
