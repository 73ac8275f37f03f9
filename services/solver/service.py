"""Solver: the single writer of landmark estimates for its region.

Consumes the matcher's assoc log (exactly once, :mod:`hdmap.runtime.stage`). Per landmark
it keeps the incremental normal-equation sums of :mod:`hdmap.mapping.estimator` (O(1) per
observation, updated in vectorised batches, in the ENU frame of the landmark's
home tile). After each batch it solves the touched landmarks and appends, per tile,
a :class:`schemas.LandmarkUpdates` entry to its update log with the landmarks whose
information matrix passed the conditioning test (revision + 1 each time), and a
removal where a landmark's estimate left its previous tile or was retired. A landmark
retired with a successor (``AssocGroup.merged_into``: the matcher found two landmarks to
be one sign) hands its sums to the successor (:meth:`LandmarkSums.merge_rows`, across
tile frames), which is then re-solved and republished.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from hdmap.geo.geodesy import enu_rotation
from hdmap.geo.tiles import TileFrames, frame_map, quadkeys_of
from hdmap.mapping import box_ranges, looming
from hdmap.mapping.estimator import LandmarkSums, Rays
from hdmap.mapping.estimator.provisional import usable
from hdmap.mapping.estimator.solve import preload
from hdmap.mapping.facing import to_wire
from hdmap.mapping.quiet import (
    QuietPasses,
    SweepPeriods,
    close_quiet,
    compact_rows,
    merge_rows,
    note_open,
)
from hdmap.runtime.stage import StageService
from schemas import (
    DROP,
    STATUS_CANDIDATE,
    STATUS_CONFIRMED,
    AssocGroup,
    DecodeError,
    Landmarks,
    LandmarkUpdates,
    LogEntry,
    Observations,
    Removals,
)
from schemas.ids import hold_key, home_tile, pass_key
from schemas.map import MapLandmarks
from services.solver.checkpoint import fold_updates
from services.solver.config import SolverConfig
from services.solver.state import SolverLandmark, SolverState

log = logging.getLogger(__name__)

_RANGE_FIELDS = ("origin", "direction", "range_m", "sigma_range_m", "sigma_pos_h")
"""The rays' columns :func:`hdmap.mapping.box_ranges.ray_terms` takes."""


@dataclass(frozen=True)
class _Links:
    """One group's links of one home tile, held until :meth:`SolverService._flush`: the
    landmarks' sum rows, the rays' pass and hold keys, and the observations (converted into
    the home's frame at the flush)."""

    rows: np.ndarray
    keys: np.ndarray
    holds: np.ndarray
    home: str
    obs: Observations
    weight: np.ndarray
    lms: list[SolverLandmark]
    t: float
    """The solver's clock after the group (the rays' open looming passes' last time)."""


@dataclass(frozen=True)
class _Solved:
    """What one publish solved: landmarks ``lms``, published ones ``ok`` (indices into
    ``lms``) and, per published one, the wire values."""

    lms: list[SolverLandmark]
    ok: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    cov: np.ndarray
    status: np.ndarray
    n_obs: np.ndarray
    n_clusters: np.ndarray
    now: float


def _unique_pairs(a: np.ndarray, b: np.ndarray) -> list[tuple[int, int]]:
    """The distinct pairs ``(a[k], b[k])`` as Python ints, in ascending order (``a`` signed,
    ``b`` unsigned 64-bit ids).

    >>> _unique_pairs(np.array([5, 3, 5]), np.array([2, 9, 2], np.uint64))
    [(3, 9), (5, 2)]
    """
    order = np.lexsort((b, a))
    sa, sb = a[order], b[order]
    first = np.ones(sa.size, bool)
    first[1:] = (sa[1:] != sa[:-1]) | (sb[1:] != sb[:-1])
    return list(zip(sa[first].tolist(), sb[first].tolist(), strict=True))


def _latest(ids: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct ``ids`` (ascending) and the largest of ``at`` (as float) for each.

    >>> [x.tolist() for x in _latest(np.array([7, 2, 7], np.uint64), np.array([1.0, 5.0, 3.0]))]
    [[2, 7], [5.0, 3.0]]
    """
    u, inv = np.unique(ids, return_inverse=True)
    out = np.full(u.size, -np.inf)
    np.maximum.at(out, inv.reshape(-1), np.asarray(at, float))
    return u, out


def cov6(c: np.ndarray) -> np.ndarray:
    """(n, 3, 3) -> (n, 6) as (ee, en, eu, nn, nu, uu)."""
    return np.stack(
        [c[:, 0, 0], c[:, 0, 1], c[:, 0, 2], c[:, 1, 1], c[:, 1, 2], c[:, 2, 2]], axis=1
    )


class SolverService(StageService):
    name = "solver"
    input_stage = "assoc"
    upstream = "matcher"
    output_stage = "update"
    hands_over = True
    output_fold = staticmethod(fold_updates)  # a new publisher starts from the checkpoints

    def __init__(self, opts, config: SolverConfig | None = None):
        super().__init__(opts)
        self.config = config or SolverConfig()
        self.frames = TileFrames()
        self.state = SolverState(self.db)
        self._quiet = QuietPasses(self.config.close_passes_after_s, clock=self._now)
        self._sweeps = SweepPeriods(self.config.sweep_every_s)
        self._reload()
        preload()  # scipy.stats for the covariance inflation, not in the first batch
        self._counts: dict[str, float] = {}
        self._snapshot_counts()

    def _reload(self) -> None:
        self._unsummed: list[_Links] = []
        """Links of this batch not yet added to the sums (:meth:`_flush`)."""
        self.sums = LandmarkSums(self.config.estimator)
        self.state.load(self.sums.unpack_rows)
        self._sweeps.restart(self.state.event_time)
        self._quiet.clear()
        note_open(self._quiet, self.sums, self.state)

    def _now(self) -> float:
        """The solver's clock (event time, :meth:`group_time`)."""
        return self.state.event_time

    @staticmethod
    def group_time(g: AssocGroup) -> float | None:
        """An assoc group's event time: the latest capture time of its linked rays, each
        no later than its ingest stamp (the matcher's :meth:`~hdmap.mapping.matching.
        Matching.entry_time` rule on what reaches the solver); None without links. The
        solver's clock is the largest so far: a function of the entries alone, so passes
        close at the same entry live, a day late and on a replay."""
        if not len(g.links):
            return None
        t = np.minimum(np.asarray(g.obs.t, float), np.asarray(g.links.received_at, float))
        t = t[np.isfinite(t)]
        return float(t.max()) if t.size else None

    def _sweep(self) -> None:
        """After a group: close the passes due if the clock entered a new sweep period
        (counted ``passes_closed``)."""
        if self._sweeps.due(self.state.event_time):
            self._flush()
            self.count("passes_closed", close_quiet(self._quiet, self.sums, self.state))
            after = max(self.config.close_passes_after_s, 0.0)
            self.state.close_loom(self.state.event_time - after)

    def _flush(self) -> None:
        """Add the links held since the last flush to the sums, in one call: the sums
        after a list of rays do not depend on how it is cut into calls
        (:meth:`LandmarkSums.accumulate`), so holding them until something reads or
        changes the sums (a settlement, a merge, a sweep, the batch's re-solve) costs one
        call per batch instead of one per group and gives the same map."""
        parts, self._unsummed = self._unsummed, []
        if not parts:
            return
        rays = self._rays(parts)
        self.sums.accumulate_parts(
            [(p.rows, p.keys, r, p.holds) for p, r in zip(parts, rays, strict=True)]
        )
        # box-range terms of all the parts' rays in one call (each part's in its home frame)
        cat = {k: np.concatenate([getattr(r, k) for r in rays]) for k in _RANGE_FIELDS}
        h, w = box_ranges.ray_terms(**cat, panel_rel_sigma=self.config.estimator.panel_rel_sigma)
        held = np.concatenate([p.holds for p in parts]) != 0
        self.state.note_ranges(
            [lm for p in parts for lm in p.lms],
            h,
            np.where(held, 0.0, w),
            np.concatenate([p.keys for p in parts]),
            np.concatenate([np.full(len(p.keys), p.t) for p in parts]),
        )

    def _rays(self, parts: list[_Links]) -> list[Rays]:
        """The parts' observations as rays in their home frames, converted once per home
        (a conversion's rows do not depend on the rows converted with them: the rays each
        part gets alone)."""
        by_home: dict[str, list[int]] = defaultdict(list)
        for k, p in enumerate(parts):
            by_home[p.home].append(k)
        out: list[Rays | None] = [None] * len(parts)
        for home, ks in by_home.items():
            obs = Observations.concat([parts[k].obs for k in ks])
            frame = self.frames(home)
            x = frame.from_geodetic(obs.lat, obs.lon, obs.h)
            d = frame.vectors_from_enu_at(obs.direction, obs.lat, obs.lon)
            start = 0
            for k in ks:
                o, w = parts[k].obs, parts[k].weight
                sl = slice(start, start + len(o))
                start = sl.stop
                out[k] = Rays(
                    x[sl],
                    d[sl],
                    o.sigma_az,
                    o.sigma_el,
                    o.sigma_pos_h,
                    o.sigma_pos_v,
                    w,
                    o.range_m,
                    o.sigma_range_m,
                )
        rays = [r for r in out if r is not None]
        assert len(rays) == len(parts)  # every part is of one home
        return rays

    def on_commit(self) -> None:
        pass

    def on_rollback(self) -> None:
        self._reload()

    def participants(self) -> list:
        return [self]

    def apply(self, entries: list[LogEntry]) -> None:
        touched: set[int] = set()
        self._unsummed = []
        self._source: dict[int, float] = {}
        self._retired: list[SolverLandmark] = []
        for e in entries:
            try:
                g = AssocGroup.from_bytes(e.body)
            except DecodeError as exc:
                self.reject(f"assoc.{exc.field}")
                continue
            self.metrics.ages(g.links.received_at)
            at = self.group_time(g)  # the clock moves, the group's passes are noted, then
            if at is not None and at > self.state.event_time:  # the due ones close
                self.state.event_time = at
            touched |= self._apply_group(g)
            self._sweep()
        touched -= {lm.id for lm in self._retired}
        self._flush()
        self._publish(sorted(touched))
        for lid in touched:  # their sums changed, published or not: save them
            self.state.put(self.state.landmarks[lid])
        self.state.save(self.sums.pack_rows)
        lms = self.state.landmarks.values()
        new_of = compact_rows(self._quiet, self.sums, lms, self.config.compact_min_rows)
        if new_of is not None:
            self.count("sums_rows_dropped", int((new_of < 0).sum()))

    def first_output(self) -> None:
        """A part of a split or a merge starts a new update log with the landmarks it has
        published (each at its next revision, as solved now): a publisher that reads the
        log from its start (one started later, after retention folded the first entries
        into checkpoints) gets the part's whole map, not only what changed since."""
        ids = sorted(i for i, lm in self.state.landmarks.items() if lm.tile)
        if not ids:
            return
        self._retired, self._source = [], {}
        self._publish(ids)
        self.state.save(self.sums.pack_rows)
        self.count("republished", len(ids))

    def _apply_group(self, g: AssocGroup) -> set[int]:
        touched: set[int] = set()
        c = g.created
        for k in range(len(c)):
            lid = int(c.id[k])
            if lid in self.state.landmarks:
                continue
            home = home_tile(lid, self.opts.zoom)
            x0 = self.frames(home).from_geodetic(c.lat[k : k + 1], c.lon[k : k + 1], c.h[k : k + 1])
            row = int(self.sums.new_rows(1, x0)[0])
            self.state.put(SolverLandmark(lid, int(c.sign_class[k]), home, row))
            touched.add(lid)
            self.count("created")
        ids = g.links.landmark_id.astype(np.uint64)
        lms = self.state.landmarks
        found = [lms.get(i) for i in ids.tolist()]
        known = np.fromiter((lm is not None for lm in found), bool, len(found))
        if (~known).any():
            self.reject("assoc.unknown_landmark", int((~known).sum()))
        keys_, holds = self._pass_keys(g)
        homes: dict[str, list[int]] = defaultdict(list)
        for k in np.flatnonzero(known).tolist():
            homes[found[k].home].append(k)  # type: ignore[union-attr]
        for home, idx in sorted(homes.items()):
            sel = np.array(idx)
            mine = [found[k] for k in idx]
            obs = g.obs.take(sel)
            rows = np.array([lm.row for lm in mine], np.int64)
            weight = g.links.weight[sel].astype(float)
            self._unsummed.append(
                _Links(rows, keys_[sel], holds[sel], home, obs, weight, mine, self.state.event_time)
            )
            self.state.note_views(mine, obs.direction)
            lid, at = _latest(ids[sel], g.links.received_at[sel])
            for i, t in zip(lid.tolist(), at.tolist(), strict=True):
                touched.add(i)
                self._source[i] = max(self._source.get(i, 0.0), t)
        self.count("observations", int(known.sum()))
        self._note_passes(ids, known, keys_)
        touched |= self.state.note_existence(g.existence)
        return touched | self._settle(g) | self._retire(g)

    def _note_passes(self, ids: np.ndarray, known: np.ndarray, keys_: np.ndarray) -> None:
        """The passes (cluster keys) this group brings rays of, and on which landmarks."""
        k = np.flatnonzero(known)
        for key, lid in _unique_pairs(keys_[k], ids[k]):
            lm = self.state.landmarks[lid]
            self._quiet.note(key, [(lm.id, lm.row)])

    @staticmethod
    def _pass_keys(g: AssocGroup) -> tuple[np.ndarray, np.ndarray]:
        """Per link, its cluster key (:func:`pass_key`) and hold key (0: not held), hashed
        once per (vehicle, pass, held) rather than per link."""
        held = g.held if g.held.size else np.zeros(len(g.links), bool)
        v = np.asarray(g.links.vehicle, np.int64) * 2 + held
        p = np.asarray(g.links.pass_id, np.uint64)
        order = np.lexsort((p, v))
        vs, ps = v[order], p[order]
        first = np.ones(v.size, bool)
        first[1:] = (vs[1:] != vs[:-1]) | (ps[1:] != ps[:-1])
        inv = np.empty(v.size, np.int64)
        inv[order] = np.cumsum(first) - 1
        uv, up = vs[first].tolist(), ps[first].tolist()
        keys = np.array(
            [pass_key(g.vehicles[u >> 1], q, bool(u & 1)) for u, q in zip(uv, up, strict=True)],
            np.int64,
        )
        holds = np.array([hold_key(g.vehicles[u >> 1]) if u & 1 else 0 for u in uv], np.int64)
        return keys[inv], holds[inv]

    def _settle(self, g: AssocGroup) -> set[int]:
        """Vehicles leaving probation: their held passes count in full or go."""
        if len(g.trust):
            self._flush()
        rows: list[int] = []
        for v, action, w in zip(g.trust.vehicle, g.trust.action, g.trust.weight, strict=True):
            key = hold_key(g.vehicles[int(v)])
            if int(action) == DROP:
                rows += self.sums.drop_held(key).tolist()
                self.count("vehicles_dropped")
            else:
                rows += self.sums.release(key, float(w)).tolist()
                self.count("vehicles_released")
        if not rows:
            return set()
        by_row = {lm.row: lm.id for lm in self.state.landmarks.values()}
        return {by_row[r] for r in rows if r in by_row}

    def _retire(self, g: AssocGroup) -> set[int]:
        """Retirements after the group's links; merged ones hand their sums over."""
        if g.retired.size:
            self._flush()
        touched: set[int] = set()
        for k, rid in enumerate(g.retired.tolist()):
            drop = self.state.landmarks.get(int(rid))
            if drop is None:
                self.reject("assoc.unknown_retired")
                continue
            if k < g.merged_into.size:
                keep = self.state.landmarks.get(int(g.merged_into[k]))
                if keep is None:  # owned by another solver: keep it rather than lose rays
                    self.reject("assoc.unknown_merge_target")
                    continue
                rot, t = frame_map(self.frames(drop.home), self.frames(keep.home))
                merge_rows(self._quiet, self.sums, keep, drop, rot, t)
                keep.view, keep.view_n = keep.view + drop.view, keep.view_n + drop.view_n
                self.state.merge_looming(keep, drop, rot, t)
                touched.add(keep.id)
                src = self._source.pop(drop.id, None)
                if src is not None:  # a merge in a later group than the links: none
                    self._source[keep.id] = max(self._source.get(keep.id, src), src)
                self.count("merged")
            self.state.delete(drop.id)
            self._retired.append(drop)
            self.count("retired")
        return touched

    def _publish(self, ids: list[int]) -> None:
        removals: dict[str, list[tuple[int, int]]] = defaultdict(list)
        for lm in self._retired:
            if lm.tile:  # it was published: the map drops it
                removals[lm.tile].append((lm.id, lm.revision + 1))
        if not ids:
            self._emit_updates({}, removals, None)
            return
        lms = [self.state.landmarks[i] for i in ids]
        sol = self.sums.solve(np.array([lm.row for lm in lms], np.int64), update_reference=False)
        n_clusters = np.asarray(sol.n_clusters)
        n_obs = np.asarray(sol.n_obs)
        good, provisional, sol_cov = usable(
            sol,
            self.config.estimator,
            self.config.provisional_passes,
            self.config.pass_bias_sigma_m,
        )
        design = 1.0 + self.config.pass_correlation * n_clusters.astype(float)
        sol_cov = sol_cov * design[:, None, None] + np.diag(
            np.square(self.config.systematic_sigma_m)
        )
        sol_x, sol_cov = self._panel_checked(lms, sol.x, sol_cov)
        for k in np.flatnonzero(~good & (n_obs == 0)):
            lm = lms[k]  # every ray taken out (a caught vehicle's): off the map until seen again
            if lm.tile:
                lm.revision += 1
                removals[lm.tile].append((lm.id, lm.revision))
                lm.tile = ""
                self.count("emptied")
        ok = np.flatnonzero(good)
        self.count("solved_ok", int(sol.ok.sum()))
        self.count("solved_provisional", int(provisional.sum()))
        if ok.size == 0:
            self._emit_updates({}, removals, None)
            return
        now = time.time()
        lat = np.empty(ok.size)
        lon = np.empty(ok.size)
        h = np.empty(ok.size)
        cov = np.empty((ok.size, 3, 3))
        floor = self.config.shared_floor()
        homes = np.array([lms[k].home for k in ok])
        for home in np.unique(homes).tolist():  # one geodetic conversion per home frame
            sel = np.flatnonzero(homes == home)
            frame = self.frames(home)
            lat[sel], lon[sel], h[sel] = frame.to_geodetic(sol_x[ok[sel]])
            r = enu_rotation(lat[sel], lon[sel]) @ frame.rotation.T
            cov[sel] = r @ sol_cov[ok[sel]] @ np.swapaxes(r, -1, -2) + floor
        tiles = quadkeys_of(lat, lon, self.opts.zoom)
        upserts: dict[str, list[int]] = defaultdict(list)
        sigma_major = np.sqrt(np.linalg.eigvalsh(cov[:, :2, :2])[:, -1])  # horizontal
        sharp = sigma_major <= self.config.confirm_max_sigma_m
        status = np.where(sol.ok[ok] & sharp, STATUS_CONFIRMED, STATUS_CANDIDATE)
        for j, k in enumerate(ok):
            lm = lms[k]
            lm.revision += 1
            tile = str(tiles[j])
            if lm.tile and lm.tile != tile:
                removals[lm.tile].append((lm.id, lm.revision))
            lm.tile = tile
            upserts[tile].append(j)
            self.state.put(lm)
        self._emit_updates(
            upserts, removals, _Solved(lms, ok, lat, lon, h, cov, status, n_obs, n_clusters, now)
        )
        self.count("updates", int(ok.size))

    def _panel_checked(
        self, lms: list[SolverLandmark], x: np.ndarray, cov: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The estimates and covariances with the panel prior
        (``SolverConfig.panel_prior``; landmarks whose box ranges put their panel more
        than ``range_check_k`` sigmas off counted ``range_discrepant``) and the looming
        check (``loom_check_k``; counted ``loom_discrepant``)."""
        mode, k = self.config.panel_prior, self.config.range_check_k
        panel = self.config.estimator.panel_rel_sigma
        k5 = box_ranges.N_SUMS
        sums = np.array([lm.ranges[:k5] for lm in lms], float).reshape(-1, k5)
        if mode != "off" and not (mode == "widen" and k <= 0):
            with np.errstate(invalid="ignore"):
                if mode == "fuse":
                    x, cov, z = box_ranges.panel_update(sums, x, cov, panel)
                else:
                    z, g, s = box_ranges.panel_discrepancy(sums, np.nan_to_num(x), cov, panel)
                    cov = box_ranges.widened_along_sight(cov, z, g, s, k, panel)
            self.count("range_discrepant", int((np.abs(np.nan_to_num(z)) > k).sum()))
        kl = self.config.loom_check_k
        if kl > 0:
            t, g, spread = looming.discrepancy(
                self.state.looming_sums(lms), np.nan_to_num(x), cov, self.config.loom_pass_sigma_m
            )
            cov = box_ranges.widened_along(cov, t, g, spread, kl)
            self.count("loom_discrepant", int((np.abs(np.nan_to_num(t)) > kl).sum()))
        return x, cov

    def _emit_updates(self, upserts: dict, removals: dict, sol: _Solved | None) -> None:
        """One update entry per tile with upserts (rows ``upserts[tile]`` of ``sol``'s
        published arrays) and removals."""
        for tile in sorted(set(upserts) | set(removals)):
            sel = np.array(upserts.get(tile, []), np.int64)
            if sol is None or sel.size == 0:
                landmarks = Landmarks.empty()
            else:
                ks = sol.ok[sel]
                lms = [sol.lms[k] for k in ks]
                facing_deg, facing_sigma_deg = to_wire(
                    self.state.facings(lms, sol.n_clusters[ks], self.config.facing_min_rays)
                )
                ex = np.array([lm.existence for lm in lms], float).reshape(-1, 4)
                landmarks = MapLandmarks(
                    facing_deg=facing_deg,
                    facing_sigma_deg=facing_sigma_deg,
                    exist_state=ex[:, 1].astype(np.uint8),
                    p_exist=ex[:, 0].astype(np.float32),
                    first_seen=ex[:, 2],
                    last_seen=ex[:, 3],
                    id=np.array([lm.id for lm in lms], np.uint64),
                    sign_class=np.array([lm.cls for lm in lms], np.uint16),
                    lat=sol.lat[sel],
                    lon=sol.lon[sel],
                    h=sol.h[sel],
                    cov=cov6(sol.cov[sel]),
                    status=sol.status[sel].astype(np.uint8),
                    n_obs=sol.n_obs[ks].astype(np.uint32),
                    n_passes=sol.n_clusters[ks].astype(np.uint32),
                    revision=np.array([lm.revision for lm in lms], np.uint64),
                    updated_at=np.full(sel.size, sol.now),
                    source_time=np.array([self._source.get(lm.id, sol.now) for lm in lms], float),
                )
            body = LandmarkUpdates(
                landmarks,
                Removals(
                    id=np.array([r[0] for r in removals.get(tile, [])], np.uint64),
                    revision=np.array([r[1] for r in removals.get(tile, [])], np.uint64),
                ),
            )
            self.emit(tile, body.to_bytes())

    def after_commit(self) -> None:
        self._snapshot_counts()

    def _snapshot_counts(self) -> None:
        self._counts = {
            "landmarks": len(self.state.landmarks),
            "published": sum(1 for lm in self.state.landmarks.values() if lm.tile),
            "state_bytes_per_landmark": float(self.sums.bytes_per_landmark),
        }

    def extra_counters(self) -> dict[str, float]:
        out = super().extra_counters()
        out.update(self._counts)
        return out
