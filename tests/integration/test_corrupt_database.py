"""A corrupt database stops its own service only (issue #17, point 3).

Real router and service processes on 127.0.0.1 (the ``stack`` fixture, ``hdmap up`` as a
subprocess). Corruption is real: pages of the SQLite file overwritten on disk. At start,
the matcher's check at open (``PRAGMA quick_check``) stops it with the file named and
exit code ``EXIT_CORRUPT``, while ingest, solver and publisher run and accept uploads;
while running, ingest meeting a damaged dedup table refuses uploads as permanent.
Every process is stopped also on failure; every wait is bounded; nothing asserts on
timing.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

from fleetsim.synthetic import make_observations
from hdmap.ops.stack import SERVICE_NAMES, Stack, Supervisor, free_port
from hdmap.ops.status import collect
from hdmap.runtime.bus import BusConfig, open_session
from hdmap.runtime.config import EXIT_CONFIG
from hdmap.runtime.service import ServiceOptions
from hdmap.runtime.store import EXIT_CORRUPT
from services.ingest.service import CORRUPT_RETRY_S
from services.matcher.service import MatcherService
from tests.support import wait_until
from tests.support.processes import running
from tests.support.uploads import upload
from vehicle.uploader import Uploader

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
PAGE = 4096


def overwrite_pages(path: Path, pages: list[int]) -> None:
    """Overwrite whole pages of a database file with garbage (what a bad disk does)."""
    with open(path, "r+b") as f:
        for pg in pages:
            f.seek((pg - 1) * PAGE)
            f.write(b"\xa5" * PAGE)
        f.flush()
        os.fsync(f.fileno())


def btree_pages(path: Path, table: str | None = None) -> list[int]:
    """Pages holding b-trees (of ``table``, or of any), from SQLite's ``dbstat``."""
    with contextlib.closing(sqlite3.connect(path)) as c:
        assert c.execute("PRAGMA page_size").fetchone()[0] == PAGE
        sql = "SELECT pageno FROM dbstat" + (" WHERE name = ?" if table else "")
        return sorted(r[0] for r in c.execute(sql + " ORDER BY pageno", (table,) if table else ()))


def corrupt_middle(path: Path) -> int:
    """Overwrite the b-tree page in the middle of a closed database file; its number."""
    assert not Path(f"{path}-wal").exists()  # closed cleanly: everything is in the file
    pages = btree_pages(path)
    middle = pages[len(pages) // 2]
    overwrite_pages(path, [middle])
    return middle


def live_services(s) -> set[str]:
    return {st.service for st in collect(s, 2.0)}


def test_a_corrupt_matcher_database_stops_the_matcher_alone(stack: Stack):
    stack.start_all()  # a first run creates every database
    stack.stop_all()
    db = stack.data_dir / "matcher-all" / "state.sqlite"
    corrupt_middle(db)

    exited = stack.start_all(isolate=True)
    matcher = stack.procs["matcher-all"]
    popen = matcher.popen
    assert exited == ["matcher-all"] and matcher.returncode == EXIT_CORRUPT
    assert matcher.permanent
    text = matcher.log_path.read_text()
    line = next(ln for ln in text.splitlines() if "database is corrupt" in ln)
    assert str(db) in line and "not restarted" in line, text
    assert "Traceback" not in text, text

    sup = Supervisor(stack)
    report = sup.check()
    assert len(report) == 1 and report[0].startswith("matcher-all stopped on a permanent fault")
    assert str(db) in report[0] and str(db) in sup.stopped["matcher-all"]
    assert sup.check() == []  # reported once, not restarted
    assert stack.procs["matcher-all"].popen is popen and not matcher.alive

    with open_session(stack.bus) as s:
        assert wait_until(lambda: live_services(s) == {"ingest", "solver", "publisher"}, 30.0, 0.2)
        ack = upload(s, "veh-1", 1, 1, 30)
        assert ack.error is None and len(ack.accepted) == 30
    assert all(stack.procs[f"{n}-all"].alive for n in SERVICE_NAMES if n != "matcher")


def test_hdmap_up_keeps_running_without_a_matcher_whose_database_is_corrupt(tmp_path):
    data = tmp_path / "var"
    MatcherService(ServiceOptions(data_dir=data)).db.close()  # the matcher's database
    db = data / "matcher-all" / "state.sqlite"
    corrupt_middle(db)
    ep = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "up.log"
    argv = [sys.executable, "-m", "hdmap.cli", "up", "--listen", ep, "--data-dir", str(data)]
    with running(argv, log) as up:

        def reported() -> bool:
            assert up.poll() is None, log.read_text()
            return "matcher-all stopped on a permanent fault" in log.read_text()

        assert wait_until(reported, 90.0, 0.5), log.read_text()
        line = next(ln for ln in log.read_text().splitlines() if "permanent fault" in ln)
        assert str(db) in line and "database is corrupt" in line, line

        with open_session(BusConfig(mode="client", connect=(ep,))) as s:
            assert wait_until(lambda: live_services(s) == {"ingest", "solver", "publisher"}, 60.0)
            ack = upload(s, "veh-1", 1, 1, 20)
            assert ack.error is None and len(ack.accepted) == 20
        res = subprocess.run(
            [sys.executable, "-m", "hdmap.cli", "status", "--timeout", "5", "--connect", ep],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=60,
        )
        assert res.returncode == 0, res.stderr
        assert all(n in res.stdout for n in ("ingest", "solver", "publisher")), res.stdout
        argvs = []
        for c in psutil.Process(up.pid).children(recursive=True):
            with contextlib.suppress(psutil.Error):
                argvs.append(" ".join(c.cmdline()))
        assert not any("service matcher" in a for a in argvs), argvs  # not restarted
        assert sum("service " in a for a in argvs) == 3, argvs
        assert log.read_text().count("matcher-all stopped") == 1
        up.send_signal(signal.SIGTERM)
        assert up.wait(60) == 1, log.read_text()  # part of the region was down
        assert "matcher-all had stopped on a permanent fault" in log.read_text()


def test_a_refused_config_stops_its_service_for_good(stack: Stack, tmp_path):
    """A config the service refuses is one error line naming the key and exit
    EXIT_CONFIG; ``hdmap up``'s supervisor does not restart it (it would fail the same way)."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[solver]\nno_such_key = 1\n")
    stack.start_router()
    p = stack.start_service("solver", (), "--config", str(bad))
    assert p.popen is not None and p.popen.wait(60) == EXIT_CONFIG
    assert p.permanent
    text = p.log_path.read_text()
    assert "configuration refused" in text and "no_such_key" in text and "Traceback" not in text
    sup = Supervisor(stack)
    report = sup.check()
    assert len(report) == 1 and "permanent fault (exit 78" in report[0], report
    assert "no_such_key" in sup.stopped["solver-all"]
    assert sup.check() == [] and stack.procs["solver-all"].popen is p.popen


def test_ingest_refuses_permanently_once_its_dedup_table_is_corrupt(stack: Stack, tmp_path):
    stack.start_router()
    stack.start_service("ingest")
    stack.wait_ready(["ingest-all"])
    db = stack.data_dir / "ingest-all" / "state.sqlite"
    with open_session(stack.bus) as s:
        assert upload(s, "veh-1", 1, 1, 40).error is None

        # damage the dedup table on disk, then write elsewhere so ingest re-reads the file
        with contextlib.closing(sqlite3.connect(db, isolation_level=None)) as c:
            busy, _, _ = c.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
            assert busy == 0
            overwrite_pages(db, btree_pages(db, "seen"))
            c.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('touched', '1')")

        for attempt in range(2):  # every upload: a permanent refusal naming the fault
            ack = upload(s, "veh-1", 2 + attempt, 1000, 30)
            assert ack.error is not None and ack.error.field == "storage", ack
            assert ack.permanent and ack.retry_after_s == CORRUPT_RETRY_S
            assert "corrupt" in ack.error.reason and len(ack.accepted) == 0
        st = {x.service: x.counters for x in collect(s)}["ingest"]
        assert st["corrupt_refusals"] == 2 and st["database_corrupt"] == 1
        assert st["storage_errors"] >= 1

        # a vehicle keeps its observations and backs off instead of retrying every 5 s
        up = Uploader("veh-2", tmp_path / "q.sqlite", batch_size=50)
        up.enqueue(1, make_observations(20, seed=9))
        res = up.flush(s, timeout=10.0)
        assert res.failed_batches == 1 and up.pending == 20
        assert res.retry_after_s >= CORRUPT_RETRY_S and "corrupt" in res.permanent_fault
        assert up.flush(s).sent == 0 and up.retry_in > 0  # waits: nothing sent
        up.close()

    assert "database is corrupt" in stack.procs["ingest-all"].log_path.read_text()
    stack.restart("ingest-all")  # at its next start the check at open stops it for good
    p = stack.procs["ingest-all"]
    assert wait_until(lambda: not p.alive, 60.0, 0.2)
    assert p.returncode == EXIT_CORRUPT
    assert f"{db}: database is corrupt" in p.log_path.read_text()
