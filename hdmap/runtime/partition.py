"""A region's database cut into sub-regions, or several joined into one (``hdmap region
split`` / ``merge``): SQL over a checkpoint (:mod:`hdmap.runtime.handover`), the
per-table rules of each service declared next to its schema (``services/*/partition.py``).

A part is a copy of the checkpoint with every row outside its region deleted, by the
service's :class:`Rules` (``split``: statements run in order, ``in_region(tile)`` a SQL
function of the part's prefixes) and the runtime's own tables:

- the output log (``log_out``, ``log_heads``, ``log_epochs``, ``log_marks``) and the
  instance id go: each part is a new producer (a new instance id on first start, its
  log from ``seq`` 1), whose consumers start its log from the beginning; its first
  entries are what the service gives a new log of a state it holds
  (:meth:`hdmap.runtime.stage.StageService.first_output`: the solver's published map);
- the input offsets keep the part's tiles (it goes on where the region left off); the
  watermarks are kept (each part's region is inside the old one);
- the durable counters and the dead letters go to the first part only, so totals over
  the instances stay what they were (``hdmap status``, :mod:`hdmap.ops.quiesce`).

Joining takes the union of the parts' rows (their regions are disjoint, so no landmark,
pending ray or tile is in two), with the service's ``merge`` rules for what both hold
(per-vehicle records: the first part's kept; clocks: the latest), counters summed and
watermarks at the lower of the two.

Pitfall: a sign within a gating radius of the border between two parts is seen by both
parts' matchers after a split (each owns its side's tiles only), as it would be by two
regions started apart: cut where the roads do not cross, or accept a second copy there.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from hdmap.geo.tiles import in_region

LOG_TABLES = ("log_out", "log_heads", "log_epochs", "log_marks", "log_checkpoint")
"""A producer's output log and its checkpoints: a part starts a new one (the old
producer's checkpoints are numbered in its log and hold other parts' tiles)."""
NEW_PRODUCER_META = ("instance", "log_truncated_through")
"""Meta keys of the old producer's identity and log."""


@dataclass(frozen=True)
class Rules:
    """A service's tables as a partition sees them.

    ``split``: SQL run in order on a part's copy, deleting what is outside the region
    (``in_region(tile)`` is true for the part's tiles). ``merge``: per table, the SQL that
    adds an attached part ``b``'s rows to the joined database (default: ``INSERT OR IGNORE
    INTO t SELECT * FROM b.t``). ``empty``: tables that must be empty in a checkpoint (the
    service's ``before_handover`` empties them).
    """

    service: str
    split: tuple[str, ...]
    """``in_region(tile)``: whether the tile is the part's; ``region_words(text)``: the
    space-separated tiles of ``text`` that are."""
    merge: dict[str, str] = field(default_factory=dict)
    empty: tuple[str, ...] = ()


def _open(path: Path, prefixes: Sequence[str]) -> sqlite3.Connection:
    conn = sqlite3.connect(path, isolation_level=None)
    regions = list(prefixes)
    conn.create_function(
        "in_region", 1, lambda t: int(t is not None and in_region(str(t), regions)),
        deterministic=True,
    )  # fmt: skip
    conn.create_function(
        "region_words", 1,
        lambda text: " ".join(w for w in str(text or "").split() if in_region(w, regions)),
        deterministic=True,
    )  # fmt: skip
    return conn


def tables(conn: sqlite3.Connection, schema: str = "main") -> list[str]:
    rows = conn.execute(
        f"SELECT name FROM {schema}.sqlite_master WHERE type='table' AND name NOT LIKE 'sqlite_%'"
    )
    return sorted(r[0] for r in rows)


def _check_empty(conn: sqlite3.Connection, rules: Rules, schema: str = "main") -> None:
    have = set(tables(conn, schema))
    for t in rules.empty:
        if t in have and conn.execute(f"SELECT 1 FROM {schema}.{t} LIMIT 1").fetchone():
            raise ValueError(f"{rules.service} checkpoint: table {t} is not empty (not paused?)")


def _as_new_producer(conn: sqlite3.Connection) -> None:
    have = set(tables(conn))
    for t in LOG_TABLES:
        if t in have:
            conn.execute(f"DELETE FROM {t}")
    if "meta" in have:
        marks = ",".join("?" * len(NEW_PRODUCER_META))
        conn.execute(f"DELETE FROM meta WHERE key IN ({marks})", NEW_PRODUCER_META)


def _copy(checkpoint: Path, out: Path, rules: Rules) -> None:
    """``out`` (which must not exist) as a copy of a checkpoint the service has made whole."""
    if out.exists():
        raise FileExistsError(f"{out}: a data dir is there already")
    out.parent.mkdir(parents=True, exist_ok=True)
    src = sqlite3.connect(checkpoint)
    try:
        _check_empty(src, rules)
        dst = sqlite3.connect(out)
        src.backup(dst)
        dst.close()
    finally:
        src.close()


def split(checkpoint: Path, out: Path, prefixes: Sequence[str], rules: Rules, first: bool) -> None:
    """Write ``out``: the checkpoint's rows of region ``prefixes`` (``first``: with the
    counters and dead letters)."""
    _copy(checkpoint, out, rules)
    conn = _open(out, prefixes)
    try:
        conn.execute("BEGIN")
        _as_new_producer(conn)
        have = set(tables(conn))
        if "offsets" in have:
            conn.execute("DELETE FROM offsets WHERE NOT in_region(tile)")
        if not first:
            for t in ("counters", "dead_letters"):
                if t in have:
                    conn.execute(f"DELETE FROM {t}")
        for sql in rules.split:
            conn.execute(sql)
        conn.execute("COMMIT")
        conn.execute("VACUUM")
    finally:
        conn.close()


def merge(checkpoints: Sequence[Path], out: Path, rules: Rules) -> None:
    """Write ``out``: the union of the checkpoints (regions that do not overlap)."""
    if len(checkpoints) < 2:
        raise ValueError("merge: at least two parts")
    _copy(checkpoints[0], out, rules)
    conn = _open(out, [])
    try:
        _as_new_producer(conn)
        zoom = _meta(conn, "main", "zoom")
        for cp in checkpoints[1:]:
            conn.execute("ATTACH DATABASE ? AS b", (str(cp),))
            try:
                if _meta(conn, "b", "zoom") != zoom:
                    raise ValueError(f"{cp}: another zoom than {checkpoints[0]}")
                _check_empty(conn, rules, "b")
                conn.execute("BEGIN")
                _join(conn, rules)
                conn.execute("COMMIT")
            finally:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                conn.execute("DETACH DATABASE b")
        conn.execute("VACUUM")
    finally:
        conn.close()


_RUNTIME_MERGE = {
    "counters": "INSERT INTO counters SELECT * FROM b.counters WHERE true "
    "ON CONFLICT(kind, name) DO UPDATE SET value = value + excluded.value",
    "watermarks": "INSERT INTO watermarks SELECT * FROM b.watermarks WHERE true "
    "ON CONFLICT(stage, producer) DO UPDATE SET gseq = MIN(gseq, excluded.gseq)",
    "meta": "INSERT OR IGNORE INTO meta SELECT * FROM b.meta",
    "dead_letters": "INSERT INTO dead_letters SELECT * FROM b.dead_letters",
}


def _join(conn: sqlite3.Connection, rules: Rules) -> None:
    mine = set(tables(conn))
    for t in tables(conn, "b"):
        if t in LOG_TABLES:
            continue
        if t not in mine:
            sql = conn.execute(
                "SELECT sql FROM b.sqlite_master WHERE type='table' AND name=?", (t,)
            ).fetchone()[0]
            conn.execute(sql)
        stmt = rules.merge.get(t) or _RUNTIME_MERGE.get(t)
        conn.execute(stmt or f"INSERT OR IGNORE INTO {t} SELECT * FROM b.{t}")


def _meta(conn: sqlite3.Connection, schema: str, key: str) -> str | None:
    try:
        row = conn.execute(f"SELECT value FROM {schema}.meta WHERE key=?", (key,)).fetchone()
    except sqlite3.OperationalError:
        return None
    return None if row is None else str(row[0])
