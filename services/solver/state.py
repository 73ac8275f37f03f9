"""The solver's per-landmark records and their persistence (sums rows live in the estimator)."""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass

import numpy as np

from hdmap.runtime.store import id_from_sql, id_to_sql

SCHEMA = """
CREATE TABLE IF NOT EXISTS landmarks (
    id INTEGER PRIMARY KEY, cls INTEGER NOT NULL, home TEXT NOT NULL, tile TEXT NOT NULL,
    revision INTEGER NOT NULL, sums BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS clock (name TEXT PRIMARY KEY, t REAL NOT NULL) WITHOUT ROWID;
"""


@dataclass
class SolverLandmark:
    id: int
    cls: int
    home: str
    row: int
    tile: str = ""
    """Tile it was last published in ('' = never published)."""
    revision: int = 0


class SolverState:
    def __init__(self, conn: sqlite3.Connection):
        self._conn = conn
        conn.executescript(SCHEMA)
        self.landmarks: dict[int, SolverLandmark] = {}
        self._dirty: set[int] = set()
        self._deleted: set[int] = set()
        self.event_time = 0.0
        """The solver's clock: event time, monotone, saved with the landmarks
        (:meth:`services.solver.service.SolverService.group_time`)."""

    def put(self, lm: SolverLandmark) -> None:
        self.landmarks[lm.id] = lm
        self._dirty.add(lm.id)

    def delete(self, lid: int) -> SolverLandmark:
        self._dirty.discard(lid)
        self._deleted.add(lid)
        return self.landmarks.pop(lid)

    def save(self, pack_rows) -> None:
        self._conn.executemany(
            "DELETE FROM landmarks WHERE id=?", [(id_to_sql(i),) for i in sorted(self._deleted)]
        )
        self._deleted.clear()
        dirty = [self.landmarks[i] for i in sorted(self._dirty)]
        blobs = pack_rows(np.array([lm.row for lm in dirty], np.int64)) if dirty else []
        self._conn.executemany(
            "INSERT OR REPLACE INTO landmarks(id, cls, home, tile, revision, sums) "
            "VALUES (?,?,?,?,?,?)",
            [
                (id_to_sql(lm.id), lm.cls, lm.home, lm.tile, lm.revision, blob)
                for lm, blob in zip(dirty, blobs, strict=True)
            ],
        )
        self._dirty.clear()
        self._conn.execute(
            "INSERT OR REPLACE INTO clock(name, t) VALUES ('event', ?)", (self.event_time,)
        )

    def load(self, unpack_rows) -> None:
        self.landmarks.clear()
        self._dirty.clear()
        self._deleted.clear()
        rows = self._conn.execute(
            "SELECT id, cls, home, tile, revision, sums FROM landmarks ORDER BY id"
        ).fetchall()
        srows = unpack_rows([r[5] for r in rows]) if rows else []
        for r, srow in zip(rows, srows, strict=True):
            lid = id_from_sql(r[0])
            self.landmarks[lid] = SolverLandmark(lid, int(r[1]), r[2], int(srow), r[3], int(r[4]))
        clock = self._conn.execute("SELECT t FROM clock WHERE name='event'").fetchone()
        self.event_time = 0.0 if clock is None else float(clock[0])
