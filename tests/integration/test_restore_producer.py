"""A producer restored alone from an old backup under load (issue 20, producer epochs):
router, ingest, matcher, solver and publisher as processes on 127.0.0.1, real SQLite.

A vehicle uploads without pause. Ingest's database is copied online (SQLite's backup API)
early on; later, with the matcher caught up, ingest is stopped and its database replaced
by that copy (its disk was lost), and started again while the vehicle keeps uploading
(its uploads fail while ingest is down and are sent again). The restored ingest numbers
its new log entries with the seq values of the entries it wrote after the copy, which
the matcher already applied; before epochs the matcher dropped them as duplicates. Every
acknowledged observation must reach the matcher once: its ``received`` count equals the
acknowledged count, and it resynchronised (``resyncs``, a log line).

What no design can keep: observations acknowledged after the copy that no consumer had
received when the disk was lost; the test stops ingest once the matcher has them.
"""

from __future__ import annotations

import shutil
import sqlite3
import threading
import time

import pytest

from hdmap.ops.quiesce import totals
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from tests.support import wait_until
from tests.support.uploads import upload

pytestmark = pytest.mark.integration

N = 20
"""Observations per upload."""


class Vehicle(threading.Thread):
    """Uploads batches of ``N`` new observations until stopped; counts what is acked."""

    def __init__(self, session):
        super().__init__(daemon=True)
        self.s = session
        self.acked = 0
        self.refused = 0
        self.batch = 0
        self.stop = threading.Event()
        self.paused = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            if self.paused.is_set():
                time.sleep(0.02)
                continue
            try:
                ack = upload(self.s, "veh-1", self.batch + 1, self.batch * N, N)
            except AssertionError:  # no ingest answered (it is down): send again
                self.refused += 1
                time.sleep(0.1)
                continue
            if ack.error is not None or len(ack.accepted) != N:
                self.refused += 1
                time.sleep(0.1)
                continue
            self.acked += N
            self.batch += 1
            time.sleep(0.01)


def received(s) -> float:
    return totals(collect(s, 2.0)).get("matcher", {}).get("received", -1)


def test_a_producer_restored_from_an_old_backup_loses_nothing_acknowledged(stack, tmp_path):
    stack.start_all()
    db = stack.data_dir / "ingest-all" / "state.sqlite"
    backup = tmp_path / "ingest-backup.sqlite"
    with open_session(stack.bus) as s:
        v = Vehicle(s)
        v.start()
        try:
            assert wait_until(lambda: v.acked >= 20 * N, 60.0)
            src = sqlite3.connect(db)
            dst = sqlite3.connect(backup)
            src.backup(dst)  # online, while ingest writes
            dst.close()
            src.close()
            at_backup = v.acked
            assert wait_until(lambda: v.acked >= at_backup + 40 * N, 60.0)

            v.paused.set()  # the matcher takes what ingest has, then ingest's disk is lost
            time.sleep(0.2)
            before = v.acked
            assert wait_until(lambda: received(s) == before, 60.0), (received(s), before)
            stack.stop("ingest-all")
            for suffix in ("", "-wal", "-shm"):
                (db.parent / f"state.sqlite{suffix}").unlink(missing_ok=True)
            shutil.copy(backup, db)
            stack.start_service("ingest")
            v.paused.clear()  # uploads go on while ingest starts (refused until it is up)
            stack.wait_ready(["ingest-all"], 60.0)

            assert wait_until(lambda: v.acked >= before + 60 * N, 120.0)
            v.stop.set()
            v.join(30)
            assert not v.is_alive()
            assert wait_until(lambda: received(s) == v.acked, 60.0), (received(s), v.acked)
            time.sleep(1.0)  # nothing more arrives (no entry applied twice)
            m = totals(collect(s, 2.0))["matcher"]
            assert m["received"] == v.acked, (m["received"], v.acked)
            assert m["resyncs"] >= 1 and m.get("entries_failed", 0) == 0
            print(f"acked {v.acked} (refused and resent {v.refused}), resyncs {m['resyncs']}")
        finally:
            v.stop.set()
            v.join(30)
    log = (stack.data_dir / "logs" / "matcher-all.log").read_text()
    assert "restarted from an older state" in log
