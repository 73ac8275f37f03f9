"""A producer's checkpoints: what retention deletes of a log whose entries are states,
folded per tile into one entry that stands for all of them (issue 20: a new or rebuilt
consumer starts from the producer's checkpoint plus the log's tail).

Before :class:`~hdmap.runtime.retention.LogRetention` deletes entries, a producer with a
``fold`` (the solver: the latest row of each landmark and every removal,
``services/solver/checkpoint.py``) folds them, per tile in ``gseq`` order, into table
``log_checkpoint``: the tile's state as of its last deleted entry, with that entry's
``seq``, ``gseq``, ``epoch``, ``base`` and ``gbase``. A catch-up that asks for entries
below what was deleted is then answered with the checkpoint entries of the consumer's
tiles (``LogEntry.checkpoint``) followed by the log's tail, instead of refused; the
consumer takes a checkpoint entry in place of the entries up to its ``seq``
(:meth:`hdmap.runtime.stream.LogConsumer.offer`).

Invariant: a consumer that applies a tile's checkpoint entry and then the tile's entries
after it holds what it would hold had it applied every entry: the fold of a list of
entries is the fold of its folds (each landmark's last row, all removals).
"""

from __future__ import annotations

import sqlite3
from collections import defaultdict
from collections.abc import Callable, Sequence

from hdmap.geo.tiles import in_region
from schemas import LogEntry, LogQuery

SCHEMA = """
CREATE TABLE IF NOT EXISTS log_checkpoint (
    tile TEXT PRIMARY KEY, seq INTEGER NOT NULL, gseq INTEGER NOT NULL,
    epoch INTEGER NOT NULL, base INTEGER NOT NULL, gbase INTEGER NOT NULL,
    body BLOB NOT NULL) WITHOUT ROWID;
"""

Fold = Callable[[bytes | None, Sequence[bytes]], bytes]
"""(the tile's checkpoint body or None, the bodies of its next entries in order) -> the
new checkpoint body."""

Row = tuple[str, int, int, bytes, int, int, int]
"""(tile, seq, gseq, body, epoch, base, gbase) of a log entry."""


def fold_rows(conn: sqlite3.Connection, rows: Sequence[Row], fold: Fold) -> None:
    """Fold ``rows`` (in ``gseq`` order) into their tiles' checkpoints (inside the caller's
    transaction, before it deletes them)."""
    by_tile: dict[str, list[Row]] = defaultdict(list)
    for r in rows:
        by_tile[r[0]].append(r)
    for tile, mine in sorted(by_tile.items()):
        old = conn.execute("SELECT body FROM log_checkpoint WHERE tile=?", (tile,)).fetchone()
        body = fold(None if old is None else bytes(old[0]), [bytes(r[3]) for r in mine])
        _t, seq, gseq, _b, epoch, base, gbase = mine[-1]
        conn.execute(
            "INSERT OR REPLACE INTO log_checkpoint(tile, seq, gseq, epoch, base, gbase, body) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (tile, seq, gseq, epoch, base, gbase, body),
        )


def checkpoint_entries(
    conn: sqlite3.Connection, stage: str, producer: str, req: LogQuery
) -> list[LogEntry]:
    """The checkpoint entries of the tiles of ``req``'s region past the seq it lists for
    them (a consumer that has a tile further drops its entry as a duplicate), in ``gseq``
    order."""
    listed = req.offsets.get(producer, {})
    out = []
    for tile, seq, gseq, epoch, base, gbase, body in conn.execute(
        "SELECT tile, seq, gseq, epoch, base, gbase, body FROM log_checkpoint ORDER BY gseq"
    ):
        if in_region(tile, req.prefixes) and seq > listed.get(tile, 0):
            out.append(
                LogEntry(stage, producer, tile, seq, gseq, bytes(body), epoch, base, gbase, True)
            )
    return out
