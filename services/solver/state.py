"""The solver's per-landmark records and their persistence (sums rows live in the estimator)."""

from __future__ import annotations

import heapq
import sqlite3
from dataclasses import dataclass, field

import numpy as np

from hdmap.mapping import box_ranges, looming
from hdmap.mapping.facing import Facing, facing_from_sums, summed_views
from hdmap.runtime.store import id_from_sql, id_to_sql

RANGE_SUMS = box_ranges.N_SUMS + looming.N_SUMS
"""A landmark's ``ranges``: its box-range sums, then its looming sums."""


def ranges_in_frame(ranges: np.ndarray, rot: np.ndarray | None, t: np.ndarray | None) -> np.ndarray:
    """A landmark's ``ranges`` kept in frame F as they are in frame G (``x_G = rot x_F +
    t``)."""
    k = box_ranges.N_SUMS
    return np.concatenate(
        [box_ranges.in_frame(ranges[:k], rot, t)[0], looming.in_frame(ranges[k:], rot, t)[0]]
    )


SCHEMA = """
CREATE TABLE IF NOT EXISTS landmarks (
    id INTEGER PRIMARY KEY, cls INTEGER NOT NULL, home TEXT NOT NULL, tile TEXT NOT NULL,
    revision INTEGER NOT NULL, sums BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS clock (name TEXT PRIMARY KEY, t REAL NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS views (
    id INTEGER PRIMARY KEY, e REAL NOT NULL, n REAL NOT NULL, count INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS ranges (id INTEGER PRIMARY KEY, sums BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS loom_open (
    id INTEGER NOT NULL, pass INTEGER NOT NULL, sums BLOB NOT NULL, PRIMARY KEY (id, pass));
CREATE TABLE IF NOT EXISTS existence (
    id INTEGER PRIMARY KEY, p REAL NOT NULL, state INTEGER NOT NULL, first_seen REAL NOT NULL,
    last_seen REAL NOT NULL);
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
    view: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """Sum of its rays' horizontal unit directions (East, North), for the published facing
    (:mod:`hdmap.mapping.facing`); ``views`` table (absent in an older database: zero)."""
    view_n: int = 0
    """Rays in ``view`` (a caught vehicle's rays taken out of the sums stay in it)."""
    ranges: np.ndarray = field(default_factory=lambda: np.zeros(RANGE_SUMS))
    """Its rays' box-range sums (:mod:`hdmap.mapping.box_ranges`) and looming sums
    (:mod:`hdmap.mapping.looming`) in its home frame, for the checks of its
    position against its panel (``SolverConfig.range_check_k``, ``loom_check_k``); rays of
    a vehicle on probation are left out. The looming sums hold its closed passes (those
    still open are in ``loom_open``). ``ranges`` table (absent: zero, no check; a blob of
    five, written before the looming sums: NaN for the rest, no looming check)."""
    loom_open: dict[int, np.ndarray] = field(default_factory=dict)
    """Its open passes' raw looming sums by pass key (:data:`hdmap.mapping.looming.RAW`
    numbers, then the solver's clock at the pass's last ray), closed into ``ranges`` once
    quiet for ``SolverConfig.close_passes_after_s`` (:meth:`SolverState.close_loom`): the
    slope is fitted within a whole pass however its rays were cut into groups.
    ``loom_open`` table."""
    existence: tuple[float, int, float, float] = (0.0, 0, 0.0, 0.0)
    """(probability, state, first seen, last seen) as the matcher last sent them
    (``AssocGroup.existence``); state 0: none sent yet (published as unknown)."""


class SolverState:
    def __init__(self, conn: sqlite3.Connection):
        self._conn = conn
        conn.executescript(SCHEMA)
        self.landmarks: dict[int, SolverLandmark] = {}
        self._dirty: set[int] = set()
        self._deleted: set[int] = set()
        self._loom_due: list[tuple[float, int, int]] = []
        """A min-heap of (clock at the last ray, landmark, pass) over the open looming
        passes, one entry per update (an entry whose pass has moved on since, or closed, is
        skipped when it comes up): :meth:`close_loom` takes the due ones without looking at
        the others (a landmark keeps some 50-200 passes open for the 2 hours it waits)."""
        self._loom_touched: set[tuple[int, int]] = set()
        """(landmark, pass) of the open passes changed, opened or closed since the last
        :meth:`save` (the only rows of ``loom_open`` it writes)."""
        self.event_time = 0.0
        """The solver's clock: event time, monotone, saved with the landmarks
        (:meth:`services.solver.service.SolverService.group_time`)."""

    def put(self, lm: SolverLandmark) -> None:
        self.landmarks[lm.id] = lm
        self._dirty.add(lm.id)

    def note_views(self, lms: list[SolverLandmark], direction: np.ndarray) -> None:
        """Ray ``k`` (unit ``direction[k]``, camera toward sign) was linked to ``lms[k]``
        (summed per landmark first: one update each, not one per ray)."""
        first, view, n = summed_views(np.array([lm.id for lm in lms], np.uint64), direction)
        for j, k in enumerate(first.tolist()):
            lm = lms[k]
            lm.view, lm.view_n = lm.view + view[j], lm.view_n + int(n[j])

    def note_ranges(
        self,
        lms: list[SolverLandmark],
        h: np.ndarray,
        w: np.ndarray,
        key: np.ndarray,
        t: np.ndarray,
    ) -> None:
        """Ray ``k``'s box-range terms (``h[k]``, weight ``w[k]``; 0: no range) onto
        ``lms[k]``'s box-range sums and its open pass ``key[k]`` (uint64), which was last
        added to at the solver's clock ``t[k]``; summed per landmark and pass first."""
        ranged = np.flatnonzero(w > 0)
        if not ranged.size:
            return
        ids = np.array([lms[k].id for k in ranged.tolist()], np.uint64)
        _, first, inv = np.unique(ids, return_index=True, return_inverse=True)
        box = box_ranges.summed(inv, h[ranged], w[ranged])
        for j, k in enumerate(first.tolist()):
            lm = lms[int(ranged[k])]
            lm.ranges[: box_ranges.N_SUMS] = lm.ranges[: box_ranges.N_SUMS] + box[j]
        keys = np.asarray(key, np.uint64)[ranged]
        pairs = np.stack([inv.astype(np.uint64), keys], axis=1)
        _, pfirst, pc = np.unique(pairs, axis=0, return_index=True, return_inverse=True)
        pc = pc.reshape(-1)
        raw = np.zeros((pfirst.size, looming.RAW))
        np.add.at(raw, pc, looming.raw_terms(h[ranged], w[ranged]))
        last = np.full(pfirst.size, -np.inf)
        np.maximum.at(last, pc, np.asarray(t, float)[ranged])
        for j, k in enumerate(pfirst.tolist()):
            lm, pk = lms[int(ranged[k])], int(keys[k])
            acc = lm.loom_open.get(pk)
            if acc is None:
                acc = lm.loom_open[pk] = np.append(raw[j], last[j])
            else:
                acc[: looming.RAW] += raw[j]
                acc[looming.RAW] = max(acc[looming.RAW], last[j])
            self._note_open(lm.id, pk, acc)

    def _note_open(self, lid: int, pk: int, acc: np.ndarray) -> None:
        heapq.heappush(self._loom_due, (float(acc[looming.RAW]), lid, pk))
        self._loom_touched.add((lid, pk))

    def close_loom(self, before: float) -> int:
        """Close the open looming passes whose last ray came before clock ``before`` into
        their landmarks' sums; returns how many."""
        due: dict[int, set[int]] = {}
        heap = self._loom_due
        while heap and heap[0][0] < before:
            last, lid, pk = heapq.heappop(heap)
            lm = self.landmarks.get(lid)
            acc = None if lm is None else lm.loom_open.get(pk)
            if acc is not None and acc[looming.RAW] == last:  # else moved on or gone
                due.setdefault(lid, set()).add(pk)
        n = 0
        for lid in sorted(due):
            lm = self.landmarks[lid]
            keys = [k for k in lm.loom_open if k in due[lid]]  # in the order they opened
            raw = np.array([lm.loom_open.pop(k)[: looming.RAW] for k in keys])
            lm.ranges[box_ranges.N_SUMS :] += looming.pass_sums(raw).sum(axis=0)
            self._loom_touched.update((lid, k) for k in keys)
            self.put(lm)
            n += len(keys)
        return n

    @staticmethod
    def looming_sums(lms: list[SolverLandmark]) -> np.ndarray:
        """The landmarks' looming sums (k, :data:`hdmap.mapping.looming.N_SUMS`): closed
        passes and open ones as if closed now (so a result does not depend on when a pass
        closes)."""
        out = np.array([lm.ranges[box_ranges.N_SUMS :] for lm in lms], float).reshape(
            -1, looming.N_SUMS
        )
        owner = [j for j, lm in enumerate(lms) for _ in lm.loom_open]
        if owner:  # every open pass of every landmark in one call
            raw = np.array([acc[: looming.RAW] for lm in lms for acc in lm.loom_open.values()])
            np.add.at(out, np.array(owner, np.int64), looming.pass_sums(raw))
        return out

    def merge_looming(self, keep: SolverLandmark, drop: SolverLandmark, rot, t) -> None:
        """``drop``'s box-range and looming sums, open passes too, onto ``keep`` (``x_keep =
        rot x_drop + t``); a pass open on both continues as one."""
        keep.ranges = keep.ranges + ranges_in_frame(drop.ranges, rot, t)
        for pk, acc in drop.loom_open.items():
            moved = np.append(looming.raw_in_frame(acc[: looming.RAW], rot, t)[0], acc[-1])
            mine = keep.loom_open.get(pk)
            if mine is None:
                mine = keep.loom_open[pk] = moved
            else:
                mine[: looming.RAW] += moved[: looming.RAW]
                mine[looming.RAW] = max(mine[looming.RAW], moved[looming.RAW])
            self._note_open(keep.id, pk, mine)

    def facings(self, lms: list[SolverLandmark], n_passes: np.ndarray, min_rays: int) -> Facing:
        """The landmarks' facings, over their passes as independent looks."""
        view = np.array([lm.view for lm in lms], float).reshape(-1, 2)
        return facing_from_sums(view, [lm.view_n for lm in lms], n_passes, min_rays)

    def note_existence(self, rows) -> set[int]:
        """The matcher's existence changes (:class:`schemas.tables.ExistenceRows`) onto the
        landmarks here; returns the ids they changed (to be published again)."""
        changed: set[int] = set()
        for lid, p, state, first, last in zip(
            rows.landmark_id.tolist(),
            rows.p_exist.tolist(),
            rows.state.tolist(),
            rows.first_seen.tolist(),
            rows.last_seen.tolist(),
            strict=True,
        ):
            lm = self.landmarks.get(int(lid))
            if lm is not None:
                lm.existence = (float(p), int(state), float(first), float(last))
                changed.add(lm.id)
        return changed

    def delete(self, lid: int) -> SolverLandmark:
        self._dirty.discard(lid)
        self._deleted.add(lid)
        return self.landmarks.pop(lid)

    def save(self, pack_rows) -> None:
        gone = [(id_to_sql(i),) for i in sorted(self._deleted)]
        self._conn.executemany("DELETE FROM landmarks WHERE id=?", gone)
        self._conn.executemany("DELETE FROM views WHERE id=?", gone)
        self._conn.executemany("DELETE FROM existence WHERE id=?", gone)
        self._conn.executemany("DELETE FROM ranges WHERE id=?", gone)
        self._conn.executemany("DELETE FROM loom_open WHERE id=?", gone)
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
        self._conn.executemany(
            "INSERT OR REPLACE INTO views(id, e, n, count) VALUES (?,?,?,?)",
            [(id_to_sql(lm.id), *map(float, lm.view), lm.view_n) for lm in dirty if lm.view_n],
        )
        self._conn.executemany(
            "INSERT OR REPLACE INTO ranges(id, sums) VALUES (?,?)",
            [(id_to_sql(lm.id), lm.ranges.tobytes()) for lm in dirty if lm.ranges[4] > 0],
        )
        opened, closed = [], []
        for lid, pk in sorted(self._loom_touched):
            lm = self.landmarks.get(lid)
            acc = None if lm is None else lm.loom_open.get(pk)
            if acc is None:
                closed.append((id_to_sql(lid), id_to_sql(pk)))
            else:
                opened.append((id_to_sql(lid), id_to_sql(pk), acc.tobytes()))
        self._loom_touched.clear()
        self._conn.executemany("DELETE FROM loom_open WHERE id=? AND pass=?", closed)
        self._conn.executemany(
            "INSERT OR REPLACE INTO loom_open(id, pass, sums) VALUES (?,?,?)", opened
        )
        self._conn.executemany(
            "INSERT OR REPLACE INTO existence(id, p, state, first_seen, last_seen) "
            "VALUES (?,?,?,?,?)",
            [(id_to_sql(lm.id), *lm.existence) for lm in dirty if lm.existence[1]],
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
        for i, e, n, count in self._conn.execute("SELECT id, e, n, count FROM views"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.view, lm.view_n = np.array([e, n], float), int(count)
        for i, blob in self._conn.execute("SELECT id, sums FROM ranges"):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                v = np.frombuffer(blob, float)[:RANGE_SUMS]
                lm.ranges = np.concatenate([v, np.full(RANGE_SUMS - v.size, np.nan)])
        self._loom_due.clear()
        self._loom_touched.clear()
        for i, pk, blob in self._conn.execute(
            "SELECT id, pass, sums FROM loom_open ORDER BY id, pass"
        ):
            lm = self.landmarks.get(id_from_sql(i))
            acc = np.frombuffer(blob, float)
            if lm is not None and acc.size == looming.RAW + 1:  # another layout: dropped
                lm.loom_open[id_from_sql(pk)] = acc.copy()
                self._loom_due.append((float(acc[looming.RAW]), lm.id, id_from_sql(pk)))
        heapq.heapify(self._loom_due)
        for i, p, state, first, last in self._conn.execute(
            "SELECT id, p, state, first_seen, last_seen FROM existence"
        ):
            lm = self.landmarks.get(id_from_sql(i))
            if lm is not None:
                lm.existence = (float(p), int(state), float(first), float(last))
        clock = self._conn.execute("SELECT t FROM clock WHERE name='event'").fetchone()
        self.event_time = 0.0 if clock is None else float(clock[0])
