"""Tile maps with versions: the publisher's state, in SQLite.

Three tables keep the contract "snapshot at version v = every delta up to v":

- ``current``: the newest estimate of every landmark (by revision) and its tile;
- ``dirty``: (tile, landmark) pairs changed since the tile's last published version;
- ``published`` + ``versions``: what vehicles have been told, per tile.

``apply`` folds solver updates into ``current`` (older revisions are ignored, so a
replay republishes nothing stale) and marks ``dirty``; ``flush`` turns each dirty
tile into one :class:`schemas.MapDelta` (version + 1), applies it to ``published``
and clears ``dirty``, all inside the caller's transaction. Snapshots read
``published`` only, so they always match a delta boundary.
"""

from __future__ import annotations

import logging
import sqlite3
import time

import numpy as np

from hdmap.runtime.store import i64_to_u64, u64_to_i64
from schemas import Landmarks, LandmarkUpdates, MapDelta, MapSnapshot, Removals
from schemas.map import MapLandmarks, as_map_landmarks

log = logging.getLogger(__name__)

_FIELDS = (
    "sign_class",
    "lat",
    "lon",
    "h",
    "cov",
    "status",
    "n_obs",
    "n_passes",
    "revision",
    "updated_at",
    "source_time",
    "facing_deg",
    "facing_sigma_deg",
    "exist_state",
    "p_exist",
    "first_seen",
    "last_seen",
)
_COLS = "id, " + ", ".join(_FIELDS)
_MARKS = ",".join("?" * (len(_FIELDS) + 2))  # tile, id, fields

SCHEMA = """
CREATE TABLE IF NOT EXISTS current (
    id INTEGER PRIMARY KEY, tile TEXT NOT NULL, sign_class INTEGER, lat REAL, lon REAL, h REAL,
    cov BLOB, status INTEGER, n_obs INTEGER, n_passes INTEGER, revision INTEGER,
    updated_at REAL, source_time REAL, facing_deg REAL NOT NULL DEFAULT 0,
    facing_sigma_deg REAL NOT NULL DEFAULT 0, exist_state REAL NOT NULL DEFAULT 0,
    p_exist REAL NOT NULL DEFAULT 0, first_seen REAL NOT NULL DEFAULT 0,
    last_seen REAL NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS published (
    tile TEXT NOT NULL, id INTEGER NOT NULL, sign_class INTEGER, lat REAL, lon REAL, h REAL,
    cov BLOB, status INTEGER, n_obs INTEGER, n_passes INTEGER, revision INTEGER,
    updated_at REAL, source_time REAL, facing_deg REAL NOT NULL DEFAULT 0,
    facing_sigma_deg REAL NOT NULL DEFAULT 0, exist_state REAL NOT NULL DEFAULT 0,
    p_exist REAL NOT NULL DEFAULT 0, first_seen REAL NOT NULL DEFAULT 0,
    last_seen REAL NOT NULL DEFAULT 0, PRIMARY KEY (tile, id)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS versions (tile TEXT PRIMARY KEY, version INTEGER NOT NULL)
    WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS dirty (
    tile TEXT NOT NULL, id INTEGER NOT NULL, revision INTEGER NOT NULL,
    PRIMARY KEY (tile, id)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS quarantine (
    tile TEXT NOT NULL, id INTEGER NOT NULL, field TEXT NOT NULL, reason TEXT NOT NULL,
    row BLOB NOT NULL, at REAL NOT NULL);
"""

_ADDED = (
    "facing_deg",
    "facing_sigma_deg",
    "exist_state",
    "p_exist",
    "first_seen",
    "last_seen",
)
"""Columns added to ``current`` and ``published`` after their first release (a database
from before gets them, 0 = facing or existence unknown, when it is opened)."""

# integer columns of a row (index in ``_COLS`` order) and the range their wire type holds
_INT_RANGES = {
    1: ("sign_class", 0, 2**16 - 1),
    6: ("status", 0, 2**8 - 1),
    7: ("n_obs", 0, 2**32 - 1),
    8: ("n_passes", 0, 2**32 - 1),
    9: ("revision", 0, 2**63 - 1),
}


def _rows(lm: Landmarks) -> list[tuple]:
    lm = as_map_landmarks(lm)
    ids = u64_to_i64(lm.id)
    cov = np.ascontiguousarray(lm.cov, dtype="<f8")
    return [
        (
            int(ids[i]),
            int(lm.sign_class[i]),
            float(lm.lat[i]),
            float(lm.lon[i]),
            float(lm.h[i]),
            cov[i].tobytes(),
            int(lm.status[i]),
            int(lm.n_obs[i]),
            int(lm.n_passes[i]),
            int(lm.revision[i]),
            float(lm.updated_at[i]),
            float(lm.source_time[i]),
            float(lm.facing_deg[i]),
            float(lm.facing_sigma_deg[i]),
            int(lm.exist_state[i]),
            float(lm.p_exist[i]),
            float(lm.first_seen[i]),
            float(lm.last_seen[i]),
        )
        for i in range(len(lm))
    ]


def landmarks_from_rows(rows: list[tuple]) -> MapLandmarks:
    """Rows (id, sign_class, ..., source_time, facing_deg, facing_sigma_deg, exist_state,
    p_exist, first_seen, last_seen) as in ``_COLS``."""
    if not rows:
        return MapLandmarks.empty()
    cols = list(zip(*rows, strict=True))
    return MapLandmarks(
        id=i64_to_u64(np.array(cols[0], np.int64)),
        sign_class=np.array(cols[1], np.uint16),
        lat=np.array(cols[2], float),
        lon=np.array(cols[3], float),
        h=np.array(cols[4], float),
        cov=np.frombuffer(b"".join(cols[5]), "<f8").reshape(-1, 6).copy(),
        status=np.array(cols[6], np.uint8),
        n_obs=np.array(cols[7], np.uint32),
        n_passes=np.array(cols[8], np.uint32),
        revision=np.array(cols[9], np.uint64),
        updated_at=np.array(cols[10], float),
        source_time=np.array(cols[11], float),
        facing_deg=np.array(cols[12], np.float32),
        facing_sigma_deg=np.array(cols[13], np.float32),
        exist_state=np.array(cols[14], float).astype(np.uint8),
        p_exist=np.array(cols[15], np.float32),
        first_seen=np.array(cols[16], float),
        last_seen=np.array(cols[17], float),
    )


def split_valid(
    rows: list[tuple],
) -> tuple[list[tuple], Landmarks, list[tuple[tuple, str, str]]]:
    """Rows (as in ``_COLS``) that the wire schema accepts, as rows and as a table, and the
    others with the field and reason that refuse them: what a vehicle would refuse is never
    sent (one bad row would make it refuse the whole delta or snapshot, and lose the
    tile)."""
    bad: list[tuple[tuple, str, str]] = []
    typed: list[tuple] = []
    for r in rows:
        why = next(
            (
                (name, f"out of range [{lo}, {hi}]")
                for i, (name, lo, hi) in _INT_RANGES.items()
                if not (isinstance(r[i], int) and lo <= r[i] <= hi)
            ),
            None,
        )
        if why is None and not (isinstance(r[5], bytes) and len(r[5]) == 48):
            why = ("cov", "not 6 float64")
        if why is None:
            typed.append(r)
        else:
            bad.append((r, *why))
    if not typed:
        return [], MapLandmarks.empty(), bad
    table = landmarks_from_rows(typed)
    flags, fld, reason = MapLandmarks.CODEC.row_errors(table)
    if not flags.any():
        return typed, table, bad
    good = [r for r, f in zip(typed, flags, strict=True) if not f]
    bad += [(r, str(fld[i]), str(reason[i])) for i, r in enumerate(typed) if flags[i]]
    return good, table.take(~flags), bad


class TileMaps:
    """The publisher's tile maps on one SQLite connection (the worker's)."""

    def __init__(self, conn: sqlite3.Connection):
        self._conn = conn
        conn.executescript(SCHEMA)
        for name in ("current", "published"):
            have = {r[1] for r in conn.execute(f"PRAGMA table_info({name})")}
            for column in _ADDED:
                if column not in have:
                    conn.execute(f"ALTER TABLE {name} ADD COLUMN {column} REAL NOT NULL DEFAULT 0")
        self.quarantined = 0
        """Rows the last :meth:`flush` quarantined instead of publishing."""

    def apply(self, tile: str, upd: LandmarkUpdates) -> int:
        """Fold one solver entry for ``tile`` into ``current``; the number of changes."""
        changed = 0
        c = self._conn
        for row in _rows(upd.landmarks):
            lid, rev = row[0], row[9]
            old = c.execute("SELECT tile, revision FROM current WHERE id=?", (lid,)).fetchone()
            if old is not None and old[1] >= rev:
                continue
            if old is not None and old[0] != tile:
                self._mark(old[0], lid, rev)  # moved: the old tile loses it
            c.execute(
                f"INSERT OR REPLACE INTO current(tile, {_COLS}) VALUES ({_MARKS})",
                (tile, *row),
            )
            self._mark(tile, lid, rev)
            changed += 1
        for lid, rev in zip(
            u64_to_i64(upd.removed.id).tolist(), upd.removed.revision.tolist(), strict=True
        ):
            old = c.execute("SELECT tile, revision FROM current WHERE id=?", (lid,)).fetchone()
            if old is None or old[0] != tile or old[1] > rev:
                continue
            c.execute("DELETE FROM current WHERE id=?", (lid,))
            self._mark(tile, lid, rev)
            changed += 1
        return changed

    def _mark(self, tile: str, lid: int, rev: int) -> None:
        self._conn.execute(
            "INSERT INTO dirty(tile, id, revision) VALUES (?, ?, ?) ON CONFLICT(tile, id) "
            "DO UPDATE SET revision=MAX(revision, excluded.revision)",
            (tile, lid, rev),
        )

    def dirty_tiles(self) -> list[str]:
        return [r[0] for r in self._conn.execute("SELECT DISTINCT tile FROM dirty")]

    def flush(self, now: float | None = None, max_tiles: int = 10_000) -> list[MapDelta]:
        """One delta per dirty tile (version + 1), applied to ``published``."""
        now = time.time() if now is None else now
        c = self._conn
        deltas = []
        self.quarantined = 0
        for tile in self.dirty_tiles()[:max_tiles]:
            marks = c.execute("SELECT id, revision FROM dirty WHERE tile=?", (tile,)).fetchall()
            ids = [m[0] for m in marks]
            upserts: list[tuple] = []
            removed: list[tuple[int, int]] = []
            for lid, rev in marks:
                row = c.execute(
                    f"SELECT {_COLS} FROM current WHERE id=? AND tile=?", (lid, tile)
                ).fetchone()
                if row is not None:
                    upserts.append(row)
                elif c.execute(
                    "SELECT 1 FROM published WHERE tile=? AND id=?", (tile, lid)
                ).fetchone():
                    removed.append((lid, rev))
            c.executemany("DELETE FROM dirty WHERE tile=? AND id=?", [(tile, i) for i in ids])
            upserts, table, bad = split_valid(upserts)
            self._quarantine(tile, bad, now)
            if not upserts and not removed:
                continue
            c.executemany(
                f"INSERT OR REPLACE INTO published(tile, {_COLS}) VALUES ({_MARKS})",
                [(tile, *r) for r in upserts],
            )
            c.executemany(
                "DELETE FROM published WHERE tile=? AND id=?", [(tile, r[0]) for r in removed]
            )
            version = version_of(c, tile)
            c.execute(
                "INSERT OR REPLACE INTO versions(tile, version) VALUES (?, ?)", (tile, version + 1)
            )
            rem = Removals(
                id=i64_to_u64(np.array([r[0] for r in removed], np.int64)),
                revision=np.array([r[1] for r in removed], np.uint64),
            )
            deltas.append(MapDelta(tile, version, version + 1, now, table, rem))
        return deltas

    def _quarantine(self, tile: str, bad: list[tuple[tuple, str, str]], now: float) -> None:
        """Move rows the schema refuses from ``current`` to ``quarantine`` (a later valid
        revision of the landmark is applied as usual)."""
        if not bad:
            return
        c = self._conn
        for row, fld, why in bad:
            log.error(
                "publisher: landmark %d in tile %s quarantined: %s %s", row[0], tile, fld, why
            )
            c.execute("DELETE FROM current WHERE id=? AND tile=?", (row[0], tile))
            c.execute(
                "INSERT INTO quarantine(tile, id, field, reason, row, at) VALUES (?,?,?,?,?,?)",
                (tile, row[0], fld, why, repr(row).encode(), now),
            )
        self.quarantined += len(bad)

    def counts(self) -> dict[str, int]:
        c = self._conn
        return {
            "quarantine": c.execute("SELECT COUNT(*) FROM quarantine").fetchone()[0],
            "landmarks": c.execute("SELECT COUNT(*) FROM current").fetchone()[0],
            "tiles": c.execute("SELECT COUNT(*) FROM versions").fetchone()[0],
            "dirty": c.execute("SELECT COUNT(*) FROM dirty").fetchone()[0],
        }


def version_of(conn: sqlite3.Connection, tile: str) -> int:
    row = conn.execute("SELECT version FROM versions WHERE tile=?", (tile,)).fetchone()
    return 0 if row is None else int(row[0])


def snapshot(conn: sqlite3.Connection, tile: str) -> MapSnapshot:
    """:func:`read_snapshot` without the count of withheld rows."""
    return read_snapshot(conn, tile)[0]


def read_snapshot(conn: sqlite3.Connection, tile: str) -> tuple[MapSnapshot, int]:
    """The published map of one tile (any tile; an unknown one is empty at version 0) and
    how many stored rows it withheld because the schema refuses them (a row damaged on
    disk after it was published).

    Read in one transaction so the version and the rows agree.
    """
    conn.execute("BEGIN")
    try:
        version = version_of(conn, tile)
        rows = conn.execute(f"SELECT {_COLS} FROM published WHERE tile=?", (tile,)).fetchall()
    finally:
        conn.execute("COMMIT")
    _good, table, bad = split_valid(rows)
    return MapSnapshot(tile, version, table), len(bad)
