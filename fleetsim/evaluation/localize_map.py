"""The fleet's map, built in-process: simulated passes -> vehicles -> matcher -> solver.

What ``hdmap eval localize`` localises against: the map the fleet itself builds, through
the same code as the live pipeline, without a router and five processes. Per pass, a
:class:`vehicle.agent.VehicleAgent` records it (fix check, geolocation, tracks, pitch:
exactly what it would queue) and its observations become obs log entries as ingest would
write them (per upload batch of at most ``batch_size`` observations, one entry per tile
of the rays' target points, :func:`hdmap.geo.tiles.route_rays`; ``seq`` per tile,
``gseq`` overall). The entries go through a :class:`services.matcher.service.MatcherService`
and its assoc log through a :class:`services.solver.service.SolverService`, each on its own
SQLite file, one transaction per ``batch`` entries (:func:`services.matcher.replay.replay`:
the matcher's landmarks do not depend on that batching). The map is the solver's update
log folded as the publisher folds it (each landmark's latest row, removals dropped), read
with its facing columns (:func:`schemas.map.updates_from_bytes`).

Not modelled (they do not change what the map holds for clean simulated uploads): ingest's
admission checks and rate limits, duplicates, absences, the publisher's tiles and deltas.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from fleetsim.fleet import Fleet
from hdmap.geo.tiles import DEFAULT_ZOOM, route_rays
from hdmap.runtime.config import from_mapping
from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry, Observations, ObsGroup
from schemas.map import MapLandmarks, updates_from_bytes
from services.matcher.replay import Sink, open_matcher, read_log, replay
from services.matcher.service import MatcherConfig
from services.solver.service import SolverConfig, SolverService
from vehicle.agent import VehicleAgent

DEFAULT_TARGET_RANGE_M = 20.0
"""Where a ray without a range is routed (ingest's ``IngestConfig.default_range_m``)."""


@dataclass
class ObsLog:
    """An obs log as ingest writes it (entries in ``gseq`` order)."""

    producer: str = "ingest-inproc"
    zoom: int = DEFAULT_ZOOM
    default_range_m: float = DEFAULT_TARGET_RANGE_M

    def __post_init__(self) -> None:
        self.entries: list[LogEntry] = []
        self._seq: dict[str, int] = {}

    def append(self, vehicle: str, pass_id: int, batch_id: int, obs: Observations) -> None:
        """One upload batch: one entry per tile of its rays' target points."""
        if not len(obs):
            return
        tiles = route_rays(
            obs.lat, obs.lon, obs.h, obs.direction, obs.range_m, self.zoom, self.default_range_m
        ).astype(str)
        received = float(np.max(obs.t))
        for tile in np.unique(tiles).tolist():
            body = ObsGroup(vehicle, pass_id, batch_id, received, obs.take(tiles == tile))
            seq = self._seq.get(tile, 0) + 1
            self._seq[tile] = seq
            gseq = len(self.entries) + 1
            self.entries.append(LogEntry("obs", self.producer, tile, seq, gseq, body.to_bytes()))


def fold_updates(entries: list[LogEntry]) -> MapLandmarks:
    """The map an update log leaves: each landmark's latest row, less the removed ones."""
    rows: dict[int, MapLandmarks] = {}
    for e in entries:
        u = updates_from_bytes(e.body)
        lm = u.landmarks
        for k in range(len(lm)):
            rows[int(lm.id[k])] = lm.take(np.array([k]))
        for lid in u.removed.id.tolist():
            rows.pop(int(lid), None)
    if not rows:
        return MapLandmarks.empty()
    return MapLandmarks.concat([rows[k] for k in sorted(rows)])


def solver_config(table: dict) -> SolverConfig:
    """A :class:`SolverConfig` from a ``[solver]`` table (unknown keys refused)."""
    known = {f.name for f in fields(SolverConfig)}
    return from_mapping(SolverConfig, {k: v for k, v in table.items() if k in known})


def build_map(
    fleet: Fleet,
    n_passes: int,
    work: Path,
    solver: SolverConfig | None = None,
    matcher: MatcherConfig | None = None,
    batch: int = 64,
    batch_size: int = 500,
    say: Callable[[str], None] | None = None,
) -> tuple[MapLandmarks, dict]:
    """The map of the fleet's first ``n_passes`` passes (module docstring), and counts.
    ``work`` (made if missing) holds the vehicles' queues and the services' databases."""
    work.mkdir(parents=True, exist_ok=True)
    say = say or (lambda _m: None)
    t0 = time.monotonic()
    log = ObsLog()
    agents: dict[str, VehicleAgent] = {}
    batches: dict[str, int] = {}
    n_obs = 0
    try:
        for k, p in enumerate(fleet.passes(n_passes)):
            a = agents.get(p.vehicle_id)
            if a is None:
                a = agents[p.vehicle_id] = VehicleAgent(p.vehicle_id, fleet.model, work / "queues")
            obs = a.record(p.pass_id, p.fixes, p.detections)
            n_obs += len(obs)
            for s in range(0, len(obs), batch_size):
                batches[p.vehicle_id] = batches.get(p.vehicle_id, 0) + 1
                chunk = obs.take(np.arange(s, min(s + batch_size, len(obs))))
                log.append(p.vehicle_id, p.pass_id, batches[p.vehicle_id], chunk)
            if (k + 1) % 50 == 0:
                say(f"map: {k + 1}/{n_passes} passes simulated ({time.monotonic() - t0:.0f} s)")
    finally:
        for a in agents.values():
            a.close()
    t1 = time.monotonic()
    m = open_matcher(work / "matcher", matcher)
    try:
        replay(m, log.entries, batch)
    finally:
        m.db.close()
    assoc = read_log(m.db_path, "assoc")
    t2 = time.monotonic()
    s = SolverService(ServiceOptions(data_dir=work / "solver"), solver)
    s.pubs = Sink()  # type: ignore[assignment]
    try:
        replay(s, assoc, batch)  # type: ignore[arg-type]
    finally:
        s.db.close()
    lm = fold_updates(read_log(s.db_path, "update"))
    t3 = time.monotonic()
    info = {
        "passes": n_passes,
        "observations": n_obs,
        "obs_entries": len(log.entries),
        "assoc_entries": len(assoc),
        "landmarks": len(lm),
        "seconds": {"simulate": t1 - t0, "matcher": t2 - t1, "solver": t3 - t2},
    }
    say(
        f"map: {len(lm)} landmarks from {n_passes} passes ({n_obs} observations; simulate "
        f"{t1 - t0:.0f} s, matcher {t2 - t1:.0f} s, solver {t3 - t2:.0f} s)"
    )
    return lm, info
