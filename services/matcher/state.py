"""The matcher's state in SQLite: landmark identities with gating estimates and facings,
the pending pool, vehicles' trust records, viewing directions, co-visibility and co-pass
counts, the budget records of passes that outgrew their pending budget and the current
gating tick's marks (:mod:`hdmap.mapping.tick`: a restart in the middle of a tick goes on
with it).

In memory it is a :class:`~hdmap.mapping.landmarks.LandmarkTable` (landmarks as a dict of
:class:`~hdmap.mapping.landmarks.Landmark` records by id, the pending pool as one columnar
table per tile); in SQLite one row per landmark and one per pending ray, and ``save``
writes what the transaction touched (of the pending pool: the rays added and the rays
taken out, so a save costs what the batch changed, not what the pool holds). ``load``
rebuilds the memory from the database (start, or after a failed transaction).
"""

from __future__ import annotations

import math
import sqlite3
from collections import defaultdict
from collections.abc import Callable

import numpy as np

from hdmap.mapping.landmarks import Landmark, LandmarkTable, PassBudget
from hdmap.mapping.pool import PendingTile
from hdmap.mapping.trust import PassOffsets, VehicleTrust
from hdmap.runtime.store import id_from_sql, id_to_sql, u64_to_i64
from schemas import Observations
from schemas.ids import pass_key
from services.matcher import held_links

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
CREATE TABLE IF NOT EXISTS box_ranges (id INTEGER PRIMARY KEY, sums BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS second_facings (id INTEGER PRIMARY KEY, az REAL NOT NULL);
CREATE TABLE IF NOT EXISTS panel_scales (id INTEGER PRIMARY KEY, scale REAL NOT NULL);
CREATE TABLE IF NOT EXISTS facings (
    id INTEGER PRIMARY KEY, az REAL NOT NULL, sigma REAL NOT NULL, spread REAL NOT NULL,
    known INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS untried (
    vehicle TEXT NOT NULL, obs_id INTEGER NOT NULL, PRIMARY KEY (vehicle, obs_id)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS tick (
    id INTEGER PRIMARY KEY, touched INTEGER NOT NULL, counted INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS sightings (
    id INTEGER PRIMARY KEY, in_view INTEGER NOT NULL, seen INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS covis (
    a INTEGER NOT NULL, b INTEGER NOT NULL, n INTEGER NOT NULL, PRIMARY KEY (a, b)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS copass (
    a INTEGER NOT NULL, b INTEGER NOT NULL, n INTEGER NOT NULL, PRIMARY KEY (a, b)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS clock (name TEXT PRIMARY KEY, t REAL NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS existence (
    id INTEGER PRIMARY KEY, l REAL NOT NULL, last_seen REAL NOT NULL);
CREATE TABLE IF NOT EXISTS held_absences (
    vehicle TEXT NOT NULL, seq INTEGER NOT NULL, pass_id INTEGER NOT NULL,
    landmark_id INTEGER NOT NULL, t REAL NOT NULL, frames INTEGER NOT NULL,
    PRIMARY KEY (vehicle, seq)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS misses (
    id INTEGER NOT NULL, vehicle TEXT NOT NULL, times TEXT NOT NULL, since INTEGER NOT NULL,
    PRIMARY KEY (id, vehicle)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS pass_budget (
    vehicle TEXT NOT NULL, pass_id INTEGER NOT NULL, evicted INTEGER NOT NULL,
    failed INTEGER NOT NULL, quarantined TEXT NOT NULL, last_at REAL NOT NULL,
    PRIMARY KEY (vehicle, pass_id)) WITHOUT ROWID;
"""


class MatcherState(LandmarkTable):
    """The matcher's :class:`LandmarkTable` with its persistence: ``save`` writes what the
    table marks as changed, ``load`` rebuilds the table from the database, and ``next_id``
    stores each tile's id counter as it goes up."""

    def __init__(self, conn: sqlite3.Connection):
        super().__init__(Observations.empty)
        self._conn = conn
        conn.executescript(SCHEMA)
        conn.executescript(held_links.SCHEMA)

    def next_id(self, home: str) -> int:
        """A new landmark id of ``home``; the tile's counter is written at once."""
        lid = super().next_id(home)
        self._conn.execute(
            "INSERT OR REPLACE INTO id_counters(tile, n) VALUES (?, ?)", (home, self.counters[home])
        )
        return lid

    # -- persistence --------------------------------------------------------------------------

    def save(self, pack_rows: Callable[[np.ndarray], list[bytes]]) -> None:
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
        c.executemany(
            "INSERT OR REPLACE INTO box_ranges(id, sums) VALUES (?,?)",
            [
                (r[0], np.asarray(lm.ranges, "<f8").tobytes())
                for r, lm in zip(rows, dirty, strict=True)
                if lm.ranges.any()
            ],
        )
        c.executemany(
            "INSERT OR REPLACE INTO second_facings(id, az) VALUES (?,?)",
            [
                (r[0], lm.second_facing)
                for r, lm in zip(rows, dirty, strict=True)
                if not np.isnan(lm.second_facing)
            ],
        )
        c.executemany(
            "INSERT OR REPLACE INTO panel_scales(id, scale) VALUES (?,?)",
            [(r[0], lm.scale) for r, lm in zip(rows, dirty, strict=True) if not np.isnan(lm.scale)],
        )
        c.executemany(
            "DELETE FROM panel_scales WHERE id=?",
            [(r[0],) for r, lm in zip(rows, dirty, strict=True) if np.isnan(lm.scale)],
        )
        c.executemany(
            "INSERT OR REPLACE INTO facings(id, az, sigma, spread, known) VALUES (?,?,?,?,?)",
            [
                (
                    r[0],
                    float(lm.facing[0]),
                    float(lm.facing[1]),
                    float(lm.facing[2]),
                    int(lm.facing[3] > 0),
                )
                for r, lm in zip(rows, dirty, strict=True)
            ],
        )
        c.executemany(
            "INSERT OR REPLACE INTO sightings(id, in_view, seen) VALUES (?,?,?)",
            [(r[0], lm.in_view, lm.seen) for r, lm in zip(rows, dirty, strict=True) if lm.in_view],
        )
        self._save_presence([r[0] for r in rows], dirty)
        gone = [(id_to_sql(i),) for i in sorted(self._deleted)]
        c.executemany("DELETE FROM landmarks WHERE id=?", gone)
        c.executemany("DELETE FROM views WHERE id=?", gone)
        c.executemany("DELETE FROM box_ranges WHERE id=?", gone)
        c.executemany("DELETE FROM second_facings WHERE id=?", gone)
        c.executemany("DELETE FROM panel_scales WHERE id=?", gone)
        c.executemany("DELETE FROM facings WHERE id=?", gone)
        self._save_tick()
        c.executemany("DELETE FROM sightings WHERE id=?", gone)
        c.executemany("DELETE FROM existence WHERE id=?", gone)
        c.executemany("DELETE FROM misses WHERE id=?", gone)
        for i in self._deleted:
            self.misses.forget(i)
        for table, counts in (("covis", self.covis_pairs), ("copass", self.copass)):
            pairs = sorted(counts.dirty)
            c.executemany(
                f"DELETE FROM {table} WHERE a=? AND b=?",
                [(id_to_sql(a), id_to_sql(b)) for a, b in pairs if (a, b) not in counts.counts],
            )
            c.executemany(
                f"INSERT OR REPLACE INTO {table}(a, b, n) VALUES (?,?,?)",
                [
                    (id_to_sql(a), id_to_sql(b), counts.counts[(a, b)])
                    for a, b in pairs
                    if (a, b) in counts.counts
                ],
            )
        removed = self._removed_pending
        sql_ids = u64_to_i64(np.array([i for _v, i in removed], np.uint64)).tolist()
        gone_rays = [(v, i) for (v, _i), i in zip(removed, sql_ids, strict=True)]
        c.executemany("DELETE FROM pending WHERE vehicle=? AND obs_id=?", gone_rays)
        tried = self._tried_saved
        tried_ids = u64_to_i64(np.array([i for _v, i in tried], np.uint64)).tolist()
        c.executemany(
            "DELETE FROM untried WHERE vehicle=? AND obs_id=?",
            gone_rays + [(v, i) for (v, _i), i in zip(tried, tried_ids, strict=True)],
        )
        gone_v = [(v,) for v in sorted(self._trust_gone)]
        for table in ("trust", "trust_status", "trust_pass"):
            c.executemany(f"DELETE FROM {table} WHERE vehicle=?", gone_v)
        c.execute("INSERT OR REPLACE INTO clock(name, t) VALUES ('event', ?)", (self.event_time,))
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
            if p is None or p.saved.all():
                continue
            new = np.flatnonzero(~p.saved)  # the rows added since the last save
            rec = Observations.CODEC.to_records(p.obs.take(new))
            ids = u64_to_i64(p.obs.obs_id[new]).tolist()
            c.executemany(
                "INSERT OR IGNORE INTO pending"
                "(vehicle, obs_id, pass_id, tile, added_at, received_at, rec) "
                "VALUES (?,?,?,?,?,?,?)",
                [
                    (
                        p.vehicle[i],
                        ids[j],
                        int(p.pass_id[i]),
                        tile,
                        float(p.added_at[i]),
                        float(p.received_at[i]),
                        rec[j].tobytes(),
                    )
                    for j, i in enumerate(new.tolist())
                ],
            )
            c.executemany(
                "INSERT OR IGNORE INTO untried(vehicle, obs_id) VALUES (?,?)",
                [(p.vehicle[i], ids[j]) for j, i in enumerate(new.tolist()) if not p.tried[i]],
            )
            p.saved[:] = True
        c.executemany(
            "DELETE FROM pass_budget WHERE vehicle=? AND pass_id=?", sorted(self._passes_gone)
        )
        c.executemany(
            "INSERT OR REPLACE INTO pass_budget"
            "(vehicle, pass_id, evicted, failed, quarantined, last_at) VALUES (?,?,?,?,?,?)",
            [
                (b.vehicle, b.pass_id, b.evicted, b.failed, b.quarantined, b.last_at)
                for b in (self.passes[k] for k in sorted(self._passes_dirty))
            ],
        )
        self.clear_marks()

    def _load_presence(self) -> None:
        """Existence log-odds and counted misses back into the landmarks and the ledger."""
        c = self._conn
        for i, lo, last in c.execute("SELECT id, l, last_seen FROM existence"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.exist, lm.last_seen = float(lo), float(last)
        self.misses.clear()
        by: dict[int, tuple[dict[str, list[float]], list[str]]] = {}
        for i, v, times, since in c.execute(
            "SELECT id, vehicle, times, since FROM misses ORDER BY id, vehicle"
        ):
            misses, vs = by.setdefault(id_from_sql(i), ({}, []))
            if times:
                misses[v] = [float(x) for x in times.split()]
            if since:
                vs.append(v)
        for lid, (misses, vs) in by.items():
            self.misses.put(lid, misses, vs)
        self.held_absences = {}
        for v, pid, lid, t, frames in c.execute(
            "SELECT vehicle, pass_id, landmark_id, t, frames FROM held_absences "
            "ORDER BY vehicle, seq"
        ):
            self.held_absences.setdefault(v, []).append(
                (int(pid), id_from_sql(lid), float(t), int(frames))
            )

    def _save_presence(self, sql_ids: list[int], dirty: list[Landmark]) -> None:
        """Existence log-odds and counted misses of the changed landmarks."""
        c = self._conn
        c.executemany(
            "INSERT OR REPLACE INTO existence(id, l, last_seen) VALUES (?,?,?)",
            [
                (i, lm.exist, lm.last_seen)
                for i, lm in zip(sql_ids, dirty, strict=True)
                if not math.isnan(lm.exist)
            ],
        )
        c.executemany("DELETE FROM misses WHERE id=?", [(i,) for i in sql_ids])
        out = []
        for i, lm in zip(sql_ids, dirty, strict=True):
            misses, since = self.misses.records(lm.id)
            for v in sorted(set(misses) | set(since)):
                times = " ".join(repr(x) for x in misses.get(v, []))
                out.append((i, v, times, int(v in since)))
        c.executemany("INSERT INTO misses(id, vehicle, times, since) VALUES (?,?,?,?)", out)
        dirty_v = sorted(self._held_absences_dirty)
        c.executemany("DELETE FROM held_absences WHERE vehicle=?", [(v,) for v in dirty_v])
        c.executemany(
            "INSERT INTO held_absences(vehicle, seq, pass_id, landmark_id, t, frames) "
            "VALUES (?,?,?,?,?,?)",
            [
                (v, k, pid, id_to_sql(lid), t, frames)
                for v in dirty_v
                for k, (pid, lid, t, frames) in enumerate(self.held_absences.get(v, []))
            ],
        )

    def _save_tick(self) -> None:
        """Write the current gating tick's marks that changed: all of them again when the
        tick changed (ended or started), else those of the landmarks noted since the last
        save (a tick's worth of landmarks, not rewritten at every unit)."""
        c = self._conn
        if self._tick_dirty:
            c.execute("DELETE FROM clock WHERE name='tick'")
            if self.tick_id is not None:
                c.execute("INSERT INTO clock(name, t) VALUES ('tick', ?)", (float(self.tick_id),))
            c.execute("DELETE FROM tick")
            ids = sorted(self.tick_touched | self.tick_counted)
        else:
            ids = sorted(self._tick_ids)
        c.executemany(
            "INSERT OR REPLACE INTO tick(id, touched, counted) VALUES (?,?,?)",
            [(id_to_sql(i), int(i in self.tick_touched), int(i in self.tick_counted)) for i in ids],
        )

    def load(self, unpack_rows: Callable[[list[bytes]], np.ndarray]) -> None:
        """Rebuild memory from SQLite; ``unpack_rows(blobs) -> rows`` restores the sums."""
        c = self._conn
        self.gating_version += 1
        self.landmarks.clear()
        self.by_tile.clear()
        self._indexed.clear()
        self.pending.clear()
        self._untried_tiles = set()
        self.covis_pairs.clear()
        self.copass.clear()
        self.clear_marks()
        self.passes = {
            pass_key(v, int(pid)): PassBudget(v, int(pid), int(ev), int(f), q, float(at))
            for v, pid, ev, f, q, at in c.execute(
                "SELECT vehicle, pass_id, evicted, failed, quarantined, last_at FROM pass_budget"
            )
        }
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
        self.index_trust()
        # 'ingest': the clock of a matcher from before event time (ingest time, within the
        # upload delay of it); it is replaced by 'event' at the first save
        clock = c.execute(
            "SELECT t FROM clock WHERE name IN ('event', 'ingest') ORDER BY name='event' DESC"
        ).fetchone()
        self.event_time = 0.0 if clock is None else float(clock[0])
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
        for i, az in c.execute("SELECT id, az FROM second_facings"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.second_facing = float(az)
        for i, scale in c.execute("SELECT id, scale FROM panel_scales"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.scale = float(scale)
        for i, blob in c.execute("SELECT id, sums FROM box_ranges"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.ranges = np.frombuffer(blob, "<f8").copy()
        self.unfaced = set(self.landmarks)
        for i, az, sigma, spread, known in c.execute(
            "SELECT id, az, sigma, spread, known FROM facings"
        ):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.facing = np.array([az, sigma, spread, float(known)])
                self.unfaced.discard(lm.id)
        self.tick_touched, self.tick_counted = set(), set()
        tick = c.execute("SELECT t FROM clock WHERE name='tick'").fetchone()
        self.tick_id = None if tick is None else int(tick[0])
        for i, touched, counted in c.execute("SELECT id, touched, counted FROM tick"):
            lid = id_from_sql(i)
            if touched:
                self.tick_touched.add(lid)
            if counted:
                self.tick_counted.add(lid)
        for i, n_in, n_seen in c.execute("SELECT id, in_view, seen FROM sightings"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.in_view, lm.seen = int(n_in), int(n_seen)
        self._load_presence()
        for table, counts in (("covis", self.covis_pairs), ("copass", self.copass)):
            for a, b, n in c.execute(f"SELECT a, b, n FROM {table}"):
                counts.add(id_from_sql(a), id_from_sql(b), int(n))
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
        untried = set(c.execute("SELECT vehicle, obs_id FROM untried").fetchall())
        if untried:
            for t, p in self.pending.items():
                ids = u64_to_i64(p.obs.obs_id).tolist()
                p.tried = np.array(
                    [(v, i) not in untried for v, i in zip(p.vehicle, ids, strict=True)], bool
                )
                if not p.tried.all():
                    self._untried_tiles.add(t)
        self.clear_marks()
