"""Corruption met while running stops a stage service, as the check at open does (issue #17).

Real router, ingest and matcher processes on 127.0.0.1 (the ``stack`` fixture, every
process stopped also on failure). The matcher applies a first upload; then pages of its
database are overwritten on disk; the next upload makes its transaction meet the damage,
and the matcher ends with exit code 65 and one line naming the file, instead of replaying
and failing in a loop. Every wait is bounded; nothing asserts on timing.
"""

from __future__ import annotations

import contextlib
import sqlite3
from pathlib import Path

import pytest

from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from hdmap.runtime.store import EXIT_CORRUPT
from tests.support import wait_until
from tests.support.uploads import upload

pytestmark = pytest.mark.integration

PAGE = 4096


def damage(path: Path, tables: tuple[str, ...]) -> None:
    """Overwrite the tables' pages on disk, then write from another connection so the
    service's connection reads the file again."""
    with contextlib.closing(sqlite3.connect(path, isolation_level=None, timeout=10)) as c:
        assert wait_until(
            lambda: c.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0] == 0, 20.0, 0.1
        )
        marks = ",".join("?" * len(tables))
        sql = f"SELECT pageno FROM dbstat WHERE name IN ({marks})"
        pages = [r[0] for r in c.execute(sql, tables)]
        assert pages
        with open(path, "r+b") as f:
            for pg in pages:
                f.seek((pg - 1) * PAGE)
                f.write(b"\xa5" * PAGE)
        c.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('touched', '1')")


def counters(s, service: str) -> dict[str, float]:
    return {st.service: st.counters for st in collect(s, 2.0)}.get(service, {})


def test_a_matcher_that_meets_corruption_while_running_stops_with_exit_65(stack: Stack):
    stack.start_router()
    stack.start_service("ingest")
    stack.start_service("matcher")
    stack.wait_ready(["ingest-all", "matcher-all"])
    db = stack.data_dir / "matcher-all" / "state.sqlite"
    matcher = stack.procs["matcher-all"]
    with open_session(stack.bus) as s:
        assert upload(s, "veh-1", 1, 1, 40).error is None
        logged = counters(s, "ingest").get("log_entries", 0)
        assert logged > 0
        assert wait_until(
            lambda: counters(s, "matcher").get("entries_applied", -1) == logged, 30.0, 0.2
        )
        damage(db, ("offsets", "counters"))
        assert upload(s, "veh-1", 2, 1000, 40).error is None  # ingest is not affected
        assert wait_until(lambda: not matcher.alive, 60.0, 0.2)
    assert matcher.returncode == EXIT_CORRUPT
    text = matcher.log_path.read_text()
    lines = [ln for ln in text.splitlines() if "database is corrupt" in ln]
    assert len(lines) == 1 and str(db) in lines[0] and "stopping (exit 65" in lines[0], text
    assert "Traceback" not in text, text
    assert stack.procs["ingest-all"].alive
