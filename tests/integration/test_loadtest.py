"""``hdmap loadtest`` against a real stack: correctness of the counts, never timings.

A router and the four services run as processes (the ``stack`` fixture stops them,
also on failure); a short, slow load runs through :func:`run_load` (what the command
uses) and then once more through the command itself, against the same stack, whose
counters are durable and cumulative: the second report must still add up, from its
own before/after deltas. Every wait is bounded (load duration, upload attempts and
timeouts, drain timeout, pytest-timeout).
"""

from __future__ import annotations

import json
import shutil

import pytest

from fleetsim.loadgen import LoadConfig
from fleetsim.loadtest import REPORT_KEYS, run_load
from hdmap.cli import main as hdmap_main
from hdmap.runtime.bus import open_session
from services.matcher.replay import landmark_digest, open_matcher, read_obs_log, replay

pytestmark = pytest.mark.integration

CFG = LoadConfig(
    vehicles=4,
    rate=1000.0,
    duration_s=4.0,
    batch=250,
    subscribers=2,
    pool_passes=12,
    upload_timeout_s=10.0,
)


def check_report(r: dict, cfg: LoadConfig) -> None:
    assert set(r) == set(REPORT_KEYS)
    assert set(r["latency_s"]) == {"p50", "p95", "p99"}
    assert r["drained"] and r["started_quiet"]
    # What the vehicles got acknowledged is what ingest recorded, all of it new.
    assert r["failed"] == 0 and r["rejected"] == 0
    assert r["accepted"] == r["sent"] > 0
    ch = r["chain"]
    assert ch["acked_by_ingest"] == r["accepted"]
    assert ch["ingest_accepted"] == r["accepted"]
    assert ch["ingest_duplicates"] == r["duplicates"] <= r["retries"] * cfg.batch
    # Counts along the chain add up: every accepted observation applied exactly once.
    assert ch["matcher_received"] == ch["ingest_accepted"]
    assert ch["matcher_linked"] == ch["solver_applied"] > 0
    assert ch["matcher_entries_applied"] == ch["ingest_log_entries"] > 0
    assert ch["solver_entries_applied"] == ch["matcher_log_entries"] > 0
    assert ch["publisher_entries_applied"] == ch["solver_log_entries"] > 0
    assert all(v == 0 for v in r["losses"].values()), r["losses"]
    assert r["zero_loss"]
    # Map deltas reached the subscribed vehicles, and each carried traced landmarks.
    assert r["deltas"] > 0 and r["delta_landmarks"] > 0
    assert r["latency_samples"] == r["delta_landmarks"]
    assert r["config"]["vehicles"] == cfg.vehicles
    assert {"ingest", "matcher", "solver", "publisher"} <= set(r["services"])
    for s in r["services"].values():
        assert s["instances"] == 1 and not s["restarted"]
        assert s["cpu_s"] >= 0 and s["rss_peak_mb"] > 0


def test_loadtest_counts_add_up(stack, tmp_path):
    stack.start_all()
    with open_session(stack.bus) as session:
        first = run_load(session, CFG, drain_timeout=120.0, progress=False)
    check_report(first, CFG)

    # The command, against the same stack (cumulative counters): its JSON report.
    out = tmp_path / "report.json"
    argv = ["loadtest", "--connect", stack.listen, "--quiet", "--json", str(out)]
    argv += ["--vehicles", "3", "--rate", "600", "--duration", "3", "--batch", "250"]
    argv += ["--subscribers", "1", "--drain-timeout", "120"]
    assert hdmap_main(argv) == 0
    second = json.loads(out.read_text())
    check_report(second, LoadConfig(vehicles=3, batch=250))
    assert second["run_id"] != first["run_id"]
    # Only this run's work is counted, not the first run's.
    assert second["chain"]["ingest_accepted"] == second["accepted"]

    # The live map is the log's: the obs log replayed in-process, in other batches, gives
    # the live matcher's landmarks (gating ticks of several units, associated ahead).
    stack.stop_all()
    shutil.copytree(stack.data_dir / "matcher-all", tmp_path / "live" / "matcher-all")
    live = open_matcher(tmp_path / "live")
    want = landmark_digest(live)
    live.db.close()
    svc = open_matcher(tmp_path / "replay")
    replay(svc, read_obs_log(stack.data_dir / "ingest-all" / "state.sqlite"), 16)
    assert svc.counters["assoc_ahead"] > 0
    assert landmark_digest(svc) == want
    svc.db.close()


def test_loadtest_refuses_without_services(router_session):
    with pytest.raises(RuntimeError, match="no live"):
        run_load(router_session, CFG, drain_timeout=5.0, progress=False)
