"""Replay a captured obs log through a matcher in-process (no bus): the map a log gives.

A captured log is an ingest's ``log_out`` table (its ``state.sqlite``): the obs entries
exactly as the matcher received them, in the producer's order (``gseq``). Replayed into a
fresh :class:`~services.matcher.service.MatcherService` on its own SQLite file, in batches
of any size, each batch one transaction as the stage loop applies it.

Invariant: the matcher's landmark table after a replay equals the live matcher's that
consumed the same log, whatever the batch size (:meth:`MatcherService.apply` emits one
assoc group per entry and home tile; every timer runs on the entries' event time).
:func:`landmark_digest` summarises the table for that comparison.
Used by ``benchmarks/bench_matcher_replay.py`` (observations/s per core) and the tests.
"""

from __future__ import annotations

import hashlib
import sqlite3
from collections.abc import Callable, Mapping
from pathlib import Path

from hdmap.runtime.config import dotted_table, from_mapping
from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry
from services.matcher.service import MatcherConfig, MatcherService


class Sink:
    """Stands in for the bus: what a service publishes goes nowhere, or, with ``keep``,
    into ``sent`` (tests read it; a replay keeps nothing)."""

    def __init__(self, keep: bool = False) -> None:
        self.keep = keep
        self.sent: list[tuple[str, bytes]] = []

    def put(self, key: str, payload: bytes) -> None:
        if self.keep:
            self.sent.append((key, payload))

    def close(self) -> None:
        pass


def read_obs_log(db: Path) -> list[LogEntry]:
    """The obs entries of an ingest database (read only), in their original order."""
    return read_log(db, "obs")


def read_log(db: Path, stage: str) -> list[LogEntry]:
    """The entries a service's database holds in its output log (read only), in their
    original order, as entries of ``stage`` (a matcher's: ``assoc``; a solver's:
    ``update``)."""
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        producer = conn.execute("SELECT value FROM meta WHERE key = 'instance'").fetchone()[0]
        rows = conn.execute("SELECT gseq, tile, seq, body FROM log_out ORDER BY gseq").fetchall()
    finally:
        conn.close()
    return [LogEntry(stage, producer, tile, seq, gseq, body) for gseq, tile, seq, body in rows]


def matcher_config(overrides: Mapping[str, object]) -> MatcherConfig:
    """``MatcherConfig`` with dotted keys (``gate.chi2_gate``) set, through the services'
    own typed config loading (an unknown key is an error naming it)."""
    return from_mapping(MatcherConfig, dotted_table(overrides))


def open_matcher(data_dir: Path, config: MatcherConfig | None = None) -> MatcherService:
    """A matcher on ``data_dir`` (its state loaded if there is one), publishing nowhere."""
    svc = MatcherService(ServiceOptions(data_dir=data_dir), config)
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def replay(
    svc: MatcherService,
    entries: list[LogEntry],
    batch: int,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Apply ``entries`` in batches of ``batch``, one transaction each (as the stage loop
    does; entries already applied are skipped by the consumer's offsets)."""
    for i in range(0, len(entries), max(1, batch)):
        svc._apply_in_transaction(svc._unapplied(entries[i : i + batch]))
        if progress is not None:
            progress(min(i + batch, len(entries)))


def landmark_digest(svc: MatcherService) -> str:
    """A checksum of the matcher's landmarks (ids, classes, home tiles, gating positions
    to 1 mm) and of its pending rays' count."""
    h = hashlib.sha256()
    for lid in sorted(svc.state.landmarks):
        lm = svc.state.landmarks[lid]
        h.update(repr((lid, lm.cls, lm.home, [round(float(v), 3) for v in lm.x])).encode())
    h.update(repr(svc.state.pending_count()).encode())
    return h.hexdigest()[:16]
