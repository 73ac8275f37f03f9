"""Solver: the single writer of landmark estimates for its region.

Consumes the matcher's assoc log (exactly once, :mod:`hdmap.stage`). Per landmark
it keeps the incremental normal-equation sums of :mod:`hdmap.estimator` (O(1) per
observation, updated in vectorised batches, in the ENU frame of the landmark's
home tile). After each batch it solves the touched landmarks and appends, per tile,
a :class:`schemas.LandmarkUpdates` entry to its update log with the landmarks whose
information matrix passed the conditioning test (revision + 1 each time), and a
removal where a landmark's estimate left its previous tile.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from hdmap.estimator import EstimatorConfig, LandmarkSums, Rays
from hdmap.estimator.provisional import usable
from hdmap.geodesy import enu_rotation
from hdmap.stage import StageService
from hdmap.tiles import TileFrames, quadkeys_of
from schemas import (
    STATUS_CANDIDATE,
    STATUS_CONFIRMED,
    AssocGroup,
    DecodeError,
    Landmarks,
    LandmarkUpdates,
    LogEntry,
    Removals,
)
from services.matcher.state import pass_key
from services.solver.state import SolverLandmark, SolverState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SolverConfig:
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    provisional_passes: int = 2
    """Below the estimator's ``min_clusters`` a landmark is still published, as a
    'candidate', from this many passes on, if its information matrix is well-conditioned
    (its covariance then carries the pass-bias prior below; 0 disables)."""
    pass_bias_sigma_m: tuple[float, float, float] = (2.5, 2.5, 1.0)
    """Prior standard deviation (E, N, U) of the position error one pass shares by all its
    rays (GNSS bias): a candidate's covariance is at least this squared over its passes,
    since the between-pass spread of so few passes cannot measure it."""


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

    def __init__(self, opts, config: SolverConfig | None = None):
        super().__init__(opts)
        self.config = config or SolverConfig()
        self.frames = TileFrames()
        self.state = SolverState(self.db)
        self._reload()
        self._counts: dict[str, float] = {}
        self._snapshot_counts()

    def _reload(self) -> None:
        self.sums = LandmarkSums(self.config.estimator)
        self.state.load(self.sums.unpack_rows)

    def on_commit(self) -> None:
        pass

    def on_rollback(self) -> None:
        self._reload()

    def participants(self) -> list:
        return [self]

    def apply(self, entries: list[LogEntry]) -> None:
        touched: set[int] = set()
        self._source: dict[int, float] = {}
        for e in entries:
            try:
                g = AssocGroup.from_bytes(e.body)
            except DecodeError as exc:
                self.reject(f"assoc.{exc.field}")
                continue
            touched |= self._apply_group(g)
        self._publish(sorted(touched))
        for lid in touched:  # their sums changed, published or not: save them
            self.state.put(self.state.landmarks[lid])
        self.state.save(self.sums.pack_rows)

    def _apply_group(self, g: AssocGroup) -> set[int]:
        touched: set[int] = set()
        c = g.created
        for k in range(len(c)):
            lid = int(c.id[k])
            if lid in self.state.landmarks:
                continue
            home = self.state.home_of(lid, self.opts.zoom)
            x0 = self.frames(home).from_geodetic(c.lat[k : k + 1], c.lon[k : k + 1], c.h[k : k + 1])
            row = int(self.sums.new_rows(1, x0)[0])
            self.state.put(SolverLandmark(lid, int(c.sign_class[k]), home, row))
            touched.add(lid)
            self.count("created")
        ids = g.links.landmark_id.astype(np.uint64)
        known = np.array([int(i) in self.state.landmarks for i in ids], bool)
        if (~known).any():
            self.reject("assoc.unknown_landmark", int((~known).sum()))
        keys_ = np.array(
            [
                pass_key(g.vehicles[v], int(p))
                for v, p in zip(g.links.vehicle, g.links.pass_id, strict=True)
            ],
            np.int64,
        )
        homes: dict[str, list[int]] = defaultdict(list)
        for k in np.flatnonzero(known):
            homes[self.state.landmarks[int(ids[k])].home].append(int(k))
        for home, idx in sorted(homes.items()):
            sel = np.array(idx)
            obs = g.obs.take(sel)
            frame = self.frames(home)
            rays = Rays(
                frame.from_geodetic(obs.lat, obs.lon, obs.h),
                frame.vectors_from_enu_at(obs.direction, obs.lat, obs.lon),
                obs.sigma_az,
                obs.sigma_el,
                obs.sigma_pos_h,
                obs.sigma_pos_v,
                g.links.weight[sel].astype(float),
            )
            rows = np.array([self.state.landmarks[int(ids[k])].row for k in idx], np.int64)
            self.sums.accumulate(rows, keys_[sel], rays)
            for k in idx:
                lid = int(ids[k])
                touched.add(lid)
                self._source[lid] = max(self._source.get(lid, 0.0), float(g.links.received_at[k]))
        self.count("observations", int(known.sum()))
        return touched

    def _publish(self, ids: list[int]) -> None:
        if not ids:
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
        ok = np.flatnonzero(good)
        self.count("solved_ok", int(sol.ok.sum()))
        self.count("solved_provisional", int(provisional.sum()))
        if ok.size == 0:
            return
        now = time.time()
        lat = np.empty(ok.size)
        lon = np.empty(ok.size)
        h = np.empty(ok.size)
        cov = np.empty((ok.size, 3, 3))
        for j, k in enumerate(ok):
            frame = self.frames(lms[k].home)
            la, lo, hh = frame.to_geodetic(sol.x[k][None])
            lat[j], lon[j], h[j] = la[0], lo[0], hh[0]
            r = enu_rotation(la[0], lo[0]) @ frame.rotation.T
            cov[j] = r @ sol_cov[k] @ r.T
        tiles = quadkeys_of(lat, lon, self.opts.zoom)
        upserts: dict[str, list[int]] = defaultdict(list)
        removals: dict[str, list[tuple[int, int]]] = defaultdict(list)
        status = np.where(sol.ok[ok], STATUS_CONFIRMED, STATUS_CANDIDATE)
        for j, k in enumerate(ok):
            lm = lms[k]
            lm.revision += 1
            tile = str(tiles[j])
            if lm.tile and lm.tile != tile:
                removals[lm.tile].append((lm.id, lm.revision))
            lm.tile = tile
            upserts[tile].append(j)
            self.state.put(lm)
        for tile in sorted(set(upserts) | set(removals)):
            sel = np.array(upserts.get(tile, []), np.int64)
            ks = ok[sel]
            body = LandmarkUpdates(
                Landmarks(
                    id=np.array([lms[k].id for k in ks], np.uint64),
                    sign_class=np.array([lms[k].cls for k in ks], np.uint16),
                    lat=lat[sel],
                    lon=lon[sel],
                    h=h[sel],
                    cov=cov6(cov[sel]) if sel.size else np.zeros((0, 6)),
                    status=status[sel].astype(np.uint8),
                    n_obs=n_obs[ks].astype(np.uint32),
                    n_passes=n_clusters[ks].astype(np.uint32),
                    revision=np.array([lms[k].revision for k in ks], np.uint64),
                    updated_at=np.full(sel.size, now),
                    source_time=np.array([self._source.get(lms[k].id, now) for k in ks], float),
                ),
                Removals(
                    id=np.array([r[0] for r in removals.get(tile, [])], np.uint64),
                    revision=np.array([r[1] for r in removals.get(tile, [])], np.uint64),
                ),
            )
            self.emit(tile, body.to_bytes())
        self.count("updates", int(ok.size))

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
