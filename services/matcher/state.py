"""The matcher's state: landmark identities with gating estimates, and the pending pool.

In memory as numpy struct-of-arrays; in SQLite as one row per landmark and one per
pending ray, rewritten for what each transaction touched. ``load`` rebuilds the
memory from the database (start, or after a failed transaction).
"""

from __future__ import annotations

import sqlite3
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hdmap.mapping.trust import PassOffsets, VehicleTrust
from hdmap.runtime.store import id_from_sql, id_to_sql, u64_to_i64
from schemas import Observations
from schemas.ids import landmark_id, pass_key

_REC = Observations.CODEC.record_dtype

SCHEMA = """
CREATE TABLE IF NOT EXISTS landmarks (
    id INTEGER PRIMARY KEY, cls INTEGER NOT NULL, home TEXT NOT NULL, tile TEXT NOT NULL,
    x BLOB NOT NULL, cov BLOB NOT NULL, sums BLOB NOT NULL, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS pending (
    vehicle TEXT NOT NULL, obs_id INTEGER NOT NULL, pass_id INTEGER NOT NULL,
    tile TEXT NOT NULL, added_at REAL NOT NULL, received_at REAL NOT NULL, rec BLOB NOT NULL,
    PRIMARY KEY (vehicle, obs_id)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS id_counters (tile TEXT PRIMARY KEY, n INTEGER NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS trust (
    vehicle TEXT PRIMARY KEY, n INTEGER NOT NULL, i_ee REAL NOT NULL, i_en REAL NOT NULL,
    i_nn REAL NOT NULL, sx REAL NOT NULL, sy REAL NOT NULL,
    offered INTEGER NOT NULL, passed INTEGER NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS trust_pass (
    vehicle TEXT PRIMARY KEY, pass_id INTEGER NOT NULL, i_ee REAL NOT NULL, i_en REAL NOT NULL,
    i_nn REAL NOT NULL, sx REAL NOT NULL, sy REAL NOT NULL, bias REAL NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS trust_status (
    vehicle TEXT PRIMARY KEY, status INTEGER NOT NULL, held_homes TEXT NOT NULL,
    last_seen REAL NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS views (id INTEGER PRIMARY KEY, e REAL NOT NULL, n REAL NOT NULL);
CREATE TABLE IF NOT EXISTS covis (
    a INTEGER NOT NULL, b INTEGER NOT NULL, n INTEGER NOT NULL, PRIMARY KEY (a, b)) WITHOUT ROWID;
"""


def _pair(a: int, b: int) -> tuple[int, int]:
    """Key of an unordered pair of landmark ids."""
    return (a, b) if a < b else (b, a)


@dataclass
class Landmark:
    """One landmark's matcher-side record (the numeric state lives in the sums row)."""

    id: int
    cls: int
    home: str
    tile: str
    x: np.ndarray
    """Gating position, ECEF metres."""
    cov: np.ndarray
    """Gating covariance, local ENU, m^2."""
    row: int
    created_at: float
    view: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """Sum of the horizontal unit directions (East, North) of its rays: the side it is
    seen from (two same-class signs back to back are never one)."""


@dataclass
class PendingTile:
    """Rays routed to one tile that wait for a landmark (columnar)."""

    obs: Observations = field(default_factory=Observations.empty)
    vehicle: list[str] = field(default_factory=list)
    pass_id: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    added_at: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    received_at: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    """Ingest receipt time (latency tracing)."""
    key: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    """:func:`pass_key` of each ray's (vehicle, pass): vectorised selection of a pass."""

    def __post_init__(self) -> None:
        if self.key.size != len(self.obs):
            self.key = np.array(
                [pass_key(v, int(p)) for v, p in zip(self.vehicle, self.pass_id, strict=True)],
                np.int64,
            )

    def __len__(self) -> int:
        return len(self.obs)

    def add(
        self, obs: Observations, vehicle: str, pass_id: int, now: float, received: float
    ) -> None:
        self.obs = Observations.concat([self.obs, obs])
        self.vehicle += [vehicle] * len(obs)
        self.pass_id = np.r_[self.pass_id, np.full(len(obs), pass_id, np.int64)]
        self.added_at = np.r_[self.added_at, np.full(len(obs), now)]
        self.received_at = np.r_[self.received_at, np.full(len(obs), received)]
        self.key = np.r_[self.key, np.full(len(obs), pass_key(vehicle, pass_id), np.int64)]

    def keep(self, mask: NDArray[np.bool_]) -> None:
        self.obs = self.obs.take(mask)
        self.vehicle = [v for v, k in zip(self.vehicle, mask, strict=True) if k]
        self.pass_id = self.pass_id[mask]
        self.added_at = self.added_at[mask]
        self.received_at = self.received_at[mask]
        self.key = self.key[mask]


class MatcherState:
    """Landmarks (by id, by tile) and pending rays (by tile), with their persistence."""

    def __init__(self, conn: sqlite3.Connection):
        self._conn = conn
        conn.executescript(SCHEMA)
        self.landmarks: dict[int, Landmark] = {}
        self.by_tile: dict[str, set[int]] = defaultdict(set)
        self.pending: dict[str, PendingTile] = defaultdict(PendingTile)
        self.counters: dict[str, int] = {}
        self.trust: dict[str, VehicleTrust] = {}
        self._trust_dirty: set[str] = set()
        self._dirty: set[int] = set()
        self._pending_dirty: set[str] = set()
        self._removed_pending: list[tuple[str, int]] = []
        self.covis: dict[tuple[int, int], int] = {}
        """Images in which two landmarks of one class were both detected (a < b): then
        they are two signs, whatever their estimates say."""
        self._covis_of: dict[int, set[int]] = defaultdict(set)
        self._covis_dirty: set[tuple[int, int]] = set()
        self._deleted: set[int] = set()
        self._indexed: dict[int, str] = {}
        """The tile each landmark is filed under in ``by_tile``."""

    # -- landmarks ------------------------------------------------------------------------

    def next_id(self, home: str) -> int:
        n = self.counters.get(home, 0) + 1
        self.counters[home] = n
        self._conn.execute("INSERT OR REPLACE INTO id_counters(tile, n) VALUES (?, ?)", (home, n))
        return landmark_id(home, n)

    def put(self, lm: Landmark) -> None:
        """Store ``lm`` (also after changing it in place: ``by_tile`` follows its tile)."""
        prev = self._indexed.get(lm.id)
        if prev is not None and prev != lm.tile:
            self.by_tile[prev].discard(lm.id)
        self._indexed[lm.id] = lm.tile
        self.landmarks[lm.id] = lm
        self.by_tile[lm.tile].add(lm.id)
        self._dirty.add(lm.id)

    def add_covis(self, a: int, b: int, n: int = 1) -> None:
        k = _pair(a, b)
        self.covis[k] = self.covis.get(k, 0) + n
        self._covis_of[a].add(b)
        self._covis_of[b].add(a)
        self._covis_dirty.add(k)

    def covis_count(self, a: int, b: int) -> int:
        return self.covis.get(_pair(a, b), 0)

    def merge(self, keep: Landmark, drop: Landmark) -> None:
        """``drop`` becomes part of ``keep``: its view and co-visibility counts move over,
        its record is deleted (the caller merges the sums rows)."""
        keep.view = keep.view + drop.view
        for other, n in self._unlist(drop).items():
            if other != keep.id:
                self.add_covis(keep.id, other, n)
        self.put(keep)

    def remove(self, lm: Landmark) -> None:
        """``lm`` ends without a successor (every ray it had was taken out)."""
        self._unlist(lm)

    def _unlist(self, lm: Landmark) -> dict[int, int]:
        """Delete ``lm``'s record; returns its co-visibility counts (other id -> images),
        which are deleted with it."""
        covis = {}
        for other in sorted(self._covis_of.pop(lm.id, set())):
            k = _pair(lm.id, other)
            covis[other] = self.covis.pop(k)
            self._covis_dirty.add(k)
            self._covis_of[other].discard(lm.id)
        self.landmarks.pop(lm.id)
        self.by_tile[self._indexed.pop(lm.id)].discard(lm.id)
        self._dirty.discard(lm.id)
        self._deleted.add(lm.id)
        return covis

    def near(self, tiles: list[str]) -> list[Landmark]:
        ids = sorted(set().union(*(self.by_tile.get(t, set()) for t in tiles)))
        return [self.landmarks[i] for i in ids]

    # -- vehicles -----------------------------------------------------------------------------

    def trust_of(self, vehicle: str) -> VehicleTrust:
        """The vehicle's record, marked to be saved (the caller is about to update it)."""
        t = self.trust.get(vehicle)
        if t is None:
            t = self.trust[vehicle] = VehicleTrust()
        self._trust_dirty.add(vehicle)
        return t

    # -- pending ----------------------------------------------------------------------------

    def add_pending(
        self,
        tile: str,
        obs: Observations,
        vehicle: str,
        pass_id: int,
        now: float,
        received: float,
    ) -> None:
        if len(obs):
            self.pending[tile].add(obs, vehicle, pass_id, now, received)
            self._pending_dirty.add(tile)

    def drop_pending(self, tile: str, mask_remove: NDArray[np.bool_]) -> None:
        if not mask_remove.any():
            return
        p = self.pending[tile]
        ids = u64_to_i64(p.obs.obs_id[mask_remove]).tolist()
        vehicles = [v for v, k in zip(p.vehicle, mask_remove, strict=True) if k]
        self._removed_pending += list(zip(vehicles, ids, strict=True))
        p.keep(~mask_remove)
        self._pending_dirty.add(tile)

    def pending_count(self) -> int:
        return sum(len(p) for p in self.pending.values())

    # -- persistence --------------------------------------------------------------------------

    def save(self, pack_rows) -> None:
        """Write what changed (inside the caller's transaction)."""
        c = self._conn
        rows = []
        dirty = [self.landmarks[lid] for lid in sorted(self._dirty)]
        blobs = pack_rows(np.array([lm.row for lm in dirty], np.int64)) if dirty else []
        for lm, blob in zip(dirty, blobs, strict=True):
            lid = lm.id
            rows.append(
                (
                    id_to_sql(lid),
                    lm.cls,
                    lm.home,
                    lm.tile,
                    np.asarray(lm.x, "<f8").tobytes(),
                    np.asarray(lm.cov, "<f8").tobytes(),
                    blob,
                    lm.created_at,
                )
            )
        c.executemany(
            "INSERT OR REPLACE INTO landmarks(id, cls, home, tile, x, cov, sums, created_at) "
            "VALUES (?,?,?,?,?,?,?,?)",
            rows,
        )
        c.executemany(
            "INSERT OR REPLACE INTO views(id, e, n) VALUES (?,?,?)",
            [
                (r[0], float(lm.view[0]), float(lm.view[1]))
                for r, lm in zip(rows, dirty, strict=True)
            ],
        )
        gone = [(id_to_sql(i),) for i in sorted(self._deleted)]
        c.executemany("DELETE FROM landmarks WHERE id=?", gone)
        c.executemany("DELETE FROM views WHERE id=?", gone)
        pairs = sorted(self._covis_dirty)
        c.executemany(
            "DELETE FROM covis WHERE a=? AND b=?",
            [(id_to_sql(a), id_to_sql(b)) for a, b in pairs if (a, b) not in self.covis],
        )
        c.executemany(
            "INSERT OR REPLACE INTO covis(a, b, n) VALUES (?,?,?)",
            [
                (id_to_sql(a), id_to_sql(b), self.covis[(a, b)])
                for a, b in pairs
                if (a, b) in self.covis
            ],
        )
        c.executemany("DELETE FROM pending WHERE vehicle=? AND obs_id=?", self._removed_pending)
        c.executemany(
            "INSERT OR REPLACE INTO trust(vehicle, n, i_ee, i_en, i_nn, sx, sy, offered, passed) "
            "VALUES (?,?,?,?,?,?,?,?,?)",
            [(v, *self.trust[v].as_row()) for v in sorted(self._trust_dirty)],
        )
        c.executemany(
            "INSERT OR REPLACE INTO trust_status(vehicle, status, held_homes, last_seen) "
            "VALUES (?,?,?,?)",
            [
                (
                    v,
                    self.trust[v].status,
                    " ".join(sorted(self.trust[v].held_homes)),
                    self.trust[v].last_seen,
                )
                for v in sorted(self._trust_dirty)
            ],
        )
        c.executemany(
            "INSERT OR REPLACE INTO trust_pass(vehicle, pass_id, i_ee, i_en, i_nn, sx, sy, bias) "
            "VALUES (?,?,?,?,?,?,?,?)",
            [
                (v, *self.trust[v].current.as_row(), self.trust[v].bias_sigma_m)
                for v in sorted(self._trust_dirty)
            ],
        )
        for tile in sorted(self._pending_dirty):
            p = self.pending.get(tile)
            if p is None or not len(p):
                continue
            rec = Observations.CODEC.to_records(p.obs)
            ids = u64_to_i64(p.obs.obs_id).tolist()
            c.executemany(
                "INSERT OR IGNORE INTO pending"
                "(vehicle, obs_id, pass_id, tile, added_at, received_at, rec) "
                "VALUES (?,?,?,?,?,?,?)",
                [
                    (
                        p.vehicle[i],
                        ids[i],
                        int(p.pass_id[i]),
                        tile,
                        float(p.added_at[i]),
                        float(p.received_at[i]),
                        rec[i].tobytes(),
                    )
                    for i in range(len(p))
                ],
            )
        self.clear_marks()

    def clear_marks(self) -> None:
        self._covis_dirty.clear()
        self._deleted.clear()
        self._trust_dirty.clear()
        self._dirty.clear()
        self._pending_dirty.clear()
        self._removed_pending = []

    def load(self, unpack_rows) -> None:
        """Rebuild memory from SQLite; ``unpack_rows(blobs) -> rows`` restores the sums."""
        c = self._conn
        self.landmarks.clear()
        self.by_tile.clear()
        self._indexed.clear()
        self.pending.clear()
        self.covis.clear()
        self._covis_of.clear()
        self.clear_marks()
        self.counters = dict(c.execute("SELECT tile, n FROM id_counters").fetchall())
        self.trust = {
            r[0]: VehicleTrust(int(r[1]), *map(float, r[2:7]), int(r[7]), int(r[8]))
            for r in c.execute(
                "SELECT vehicle, n, i_ee, i_en, i_nn, sx, sy, offered, passed FROM trust"
            )
        }
        for v, pid, *sums, bias in c.execute(
            "SELECT vehicle, pass_id, i_ee, i_en, i_nn, sx, sy, bias FROM trust_pass"
        ):
            t = self.trust.get(v)
            if t is not None:
                t.current = PassOffsets(int(pid), *map(float, sums))
                t.bias_sigma_m = float(bias)
        for v, status, homes, seen in c.execute(
            "SELECT vehicle, status, held_homes, last_seen FROM trust_status"
        ):
            t = self.trust.get(v)
            if t is not None:
                t.status, t.held_homes, t.last_seen = int(status), set(homes.split()), float(seen)
        rows = c.execute(
            "SELECT id, cls, home, tile, x, cov, sums, created_at FROM landmarks ORDER BY id"
        ).fetchall()
        sums_rows = unpack_rows([r[6] for r in rows]) if rows else []
        for r, srow in zip(rows, sums_rows, strict=True):
            lid = id_from_sql(r[0])
            lm = Landmark(
                lid,
                int(r[1]),
                r[2],
                r[3],
                np.frombuffer(r[4], "<f8").copy(),
                np.frombuffer(r[5], "<f8").reshape(3, 3).copy(),
                int(srow),
                float(r[7]),
            )
            self.landmarks[lid] = lm
            self.by_tile[lm.tile].add(lid)
            self._indexed[lid] = lm.tile
        for i, e, n in c.execute("SELECT id, e, n FROM views"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.view = np.array([e, n], float)
        for a, b, n in c.execute("SELECT a, b, n FROM covis"):
            self.add_covis(id_from_sql(a), id_from_sql(b), int(n))
        prow = c.execute(
            "SELECT tile, vehicle, pass_id, added_at, received_at, rec FROM pending "
            "ORDER BY tile, added_at, vehicle, obs_id"
        ).fetchall()
        by: dict[str, list] = defaultdict(list)
        for t, v, pid, at, rec_at, rec in prow:
            by[t].append((v, pid, at, rec_at, rec))
        for t, items in by.items():
            recs = np.frombuffer(b"".join(i[4] for i in items), dtype=_REC)
            self.pending[t] = PendingTile(
                Observations.CODEC.from_records(recs),
                [i[0] for i in items],
                np.array([i[1] for i in items], np.int64),
                np.array([i[2] for i in items], float),
                np.array([i[3] for i in items], float),
            )
        self.clear_marks()
