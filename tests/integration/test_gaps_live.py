"""A forged stage entry far ahead of a tile's log (issue 20, bounded gaps), live: router,
ingest, matcher, solver and publisher as processes on 127.0.0.1.

Anyone on an open bus can publish on ``hdmap/v1/obs/**``. An entry that names the real
ingest and a real tile with a sequence number far ahead opens a gap no producer can fill.
The matcher holds it, reports the gap (``hdmap status``), retries it with a doubling delay
(not at every batch: before, every batch ran a blocking catch-up while it waited), keeps
applying the tile's real entries as they come, and gives the gap up after
``[matcher.gaps] timeout_s``. No timing assertion: each upload's time until the matcher
has applied it is printed for the record; what is asserted is the count of catch-ups,
bounded by the retry schedule and the periodic catch-up, whatever the machine's speed.
"""

from __future__ import annotations

import math
import sqlite3
import subprocess
import sys
import time

import pytest

from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from schemas import LogEntry, keys
from tests.support import wait_until
from tests.support.uploads import upload

pytestmark = pytest.mark.integration

TIMEOUT_S = 6.0
RETRY_S = 0.5
CONFIG = f"""\
[matcher.gaps]
timeout_s = {TIMEOUT_S}
retry_s = {RETRY_S}
retry_max_s = 30.0
"""
UPLOADS = 30


def matcher_counters(s) -> dict[str, float]:
    return totals(collect(s, 2.0)).get("matcher", {})


def test_a_forged_entry_far_ahead_holds_up_no_real_traffic(stack, tmp_path):
    cfg = tmp_path / "gaps.toml"
    cfg.write_text(CONFIG)
    stack.extra_service_args["matcher"] = ["--config", str(cfg)]
    stack.start_all()
    with open_session(stack.bus) as s:
        assert len(upload(s, "veh-1", 1, 0, 20).accepted) == 20
        assert wait_quiet(s, 60.0)
        db = sqlite3.connect(
            f"file:{stack.data_dir / 'ingest-all' / 'state.sqlite'}?mode=ro", uri=True
        )
        try:
            producer = db.execute("SELECT value FROM meta WHERE key = 'instance'").fetchone()[0]
            tile = db.execute("SELECT tile FROM log_out ORDER BY gseq LIMIT 1").fetchone()[0]
        finally:
            db.close()
        forged = LogEntry("obs", producer, tile, 10**12, 10**12, b"forged")
        s.put(keys.obs(tile), forged.to_bytes())
        assert wait_until(lambda: matcher_counters(s).get("gaps_open") == 1, 20.0)
        before = matcher_counters(s)
        t0 = time.monotonic()

        times = []
        for k in range(2, 2 + UPLOADS):  # the same vehicle's sightings: the same tiles
            t = time.monotonic()
            ack = upload(s, "veh-1", k, 100 * k, 20)
            assert len(ack.accepted) == 20
            want = totals(collect(s, 2.0))["ingest"]["log_entries"]
            assert wait_until(lambda w=want: matcher_counters(s).get("entries_applied") == w, 30.0)
            times.append(time.monotonic() - t)
        during = matcher_counters(s)
        window = time.monotonic() - t0
        print(f"upload -> applied by the matcher, s: {sorted(round(x, 3) for x in times)}")

        assert during["gaps_open"] == 1 and during["entries_ahead"] == 1  # still held
        # catch-ups while it waited: the retries (0.5 s doubling), the periodic ones
        # (every 5 s) and one each for the windows' edges; before, one per batch
        retries = math.ceil(math.log2(window / RETRY_S + 1)) + 1
        bound = retries + math.ceil(window / 5.0) + 2
        n = during["catchups"] - before["catchups"]
        assert n <= bound < UPLOADS, (n, bound, window)

        assert wait_until(lambda: matcher_counters(s).get("gaps_expired") == 1, 3 * TIMEOUT_S)
        after = matcher_counters(s)
        assert after["gaps_open"] == 0 and after["entries_ahead"] == 0
        assert after["lag_entries"] == 0 and after.get("entries_failed", 0) == 0
        assert wait_quiet(s, 60.0)  # everything ingest logged is applied, once

        status = subprocess.run(
            [sys.executable, "-m", "hdmap.cli", "status", "--connect", stack.listen],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert "gaps not filled in time" in status.stdout, status.stdout
    log = (stack.data_dir / "logs" / "matcher-all.log").read_text()
    assert f"gap in {producer}/{tile} not filled in {TIMEOUT_S:g} s" in log
