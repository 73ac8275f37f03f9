"""In-process matcher and solver on real SQLite, fed through their transactions.

Scene: one sign 30 m north of a road origin; passes drive north along x = -2 m with a
per-pass GNSS bias (1 m per axis) and 0.01 rad angular noise, 10 rays each.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from fleetsim.synthetic import ray_observations
from hdmap.geo.tiles import quadkeys_of
from hdmap.runtime.service import ServiceOptions
from schemas import AssocGroup, LandmarkUpdates, Links, LogEntry, NewLandmarks, Observations
from services.matcher import replay
from services.matcher.replay import open_matcher
from services.matcher.service import MatcherService
from services.solver.service import SolverConfig, SolverService

CLS = 7


SIGN = np.array([10.0, 30.0, 2.5])


LAT = 60.17


LON = 24.94


class Sink(replay.Sink):
    """Stands in for the bus: keeps what a service publishes (in ``sent``)."""

    def __init__(self) -> None:
        super().__init__(keep=True)


def tile_of(zoom: int) -> str:
    return str(quadkeys_of(np.array([LAT]), np.array([LON]), zoom)[0])


def sign_rays(frame, p: int, rng, from_north: bool = False, n: int = 10, image0: int = 0, at=SIGN):
    """One pass's rays at the sign ``at`` (obs ids unique per pass)."""
    ys = np.linspace(0.0, 22.0, n) if not from_north else np.linspace(60.0, 38.0, n)
    a = np.stack([np.full(n, 8.0 if from_north else 12.0), ys, np.full(n, 1.5)], 1)
    a_meas = a + np.r_[rng.normal(0, 1.0, 2), 0.0]  # the pass's shared bias
    v = at - a + rng.normal(0, 0.01, (n, 3)) * np.linalg.norm(at - a, axis=1)[:, None]
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    lat, lon, h = frame.to_geodetic(a_meas)
    # directions in the frame's ENU; ENU at the camera is within 1e-4 rad of it
    ids = np.arange(n) + 1000 * p + image0
    return ray_observations(lat, lon, h, d, np.arange(n) + image0, ids, CLS, sigma_ang=0.01)


def matcher(path: Path) -> MatcherService:
    svc = open_matcher(path)
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def solver(path: Path, config: SolverConfig | None = None) -> SolverService:
    svc = SolverService(ServiceOptions(data_dir=path), config)
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def assoc_entry(seq: int, tile: str, **kw) -> LogEntry:
    g = AssocGroup(
        vehicles=kw.get("vehicles", []),
        links=kw.get("links", Links.empty()),
        obs=kw.get("obs", Observations.empty()),
        created=kw.get("created", NewLandmarks.empty()),
        retired=np.array(kw.get("retired", []), np.uint64),
        merged_into=np.array(kw.get("merged_into", []), np.uint64),
    )
    return LogEntry("assoc", "matcher-test", tile, seq, seq, g.to_bytes())


def updates(svc: SolverService) -> list[LandmarkUpdates]:
    out = [LandmarkUpdates.from_bytes(LogEntry.from_bytes(p).body) for _k, p in svc.pubs.sent]
    svc.pubs.sent.clear()
    return out


def one_sign_solver(
    tmp: Path,
    config: SolverConfig,
    passes: int,
    start: np.ndarray = SIGN,
    edit: Callable[[Observations, Any], Observations] | None = None,
    cuts: int = 1,
    restart_after: int | None = None,
) -> SolverService:
    """A solver on ``tmp / "s"`` given ``passes`` passes of :func:`sign_rays` (a minute
    apart, all linked to one landmark created at ``start``; ``edit(obs, frame)`` changes a
    pass's observations first), each pass's rays in ``cuts`` assoc entries (in order);
    with ``restart_after``, the solver is restarted from its database after that many
    passes."""
    tile = tile_of(ServiceOptions().zoom)
    m = matcher(tmp / "m")  # for ids and frames only
    frame = m.frames(tile)
    lid = m.state.next_id(tile)
    lat, lon, h = frame.to_geodetic(np.asarray(start, float)[None])
    created = NewLandmarks(np.array([lid], np.uint64), np.full(1, CLS, np.uint16), lat, lon, h)
    svc = solver(tmp / "s", config)
    rng = np.random.default_rng(5)
    seq = 0
    for p in range(passes):
        obs = sign_rays(frame, p, rng)
        obs = replace(obs, t=np.full(len(obs), 1.7e9 + 60.0 * p))
        if edit is not None:
            obs = edit(obs, frame)
        for part in np.array_split(np.arange(len(obs)), cuts):
            o = obs.take(part)
            n = len(o)
            links = Links(
                np.full(n, lid, np.uint64),
                np.zeros(n, np.uint32),
                np.full(n, p, np.uint64),
                o.t + 5.0,
                np.ones(n, np.float32),
            )
            seq += 1
            kw = {"created": created} if seq == 1 else {}
            svc._apply_in_transaction(
                [assoc_entry(seq, tile, vehicles=["veh-a"], obs=o, links=links, **kw)]
            )
        if restart_after is not None and p + 1 == restart_after:
            svc.db.close()
            svc = solver(tmp / "s", config)
    m.db.close()
    return svc
