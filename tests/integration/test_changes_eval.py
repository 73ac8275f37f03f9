"""``hdmap eval changes --quick``: the map follows the world, end to end (issue 21).

A router and the four services as processes (started and stopped by the command), a fleet
of six vehicles that follows the published map and reports the mapped signs it passed
and did not detect, one of them blind after the warm-up; a town where one sign is taken
down, one moved and one put up (fixed seed). Checks the JSON and the PNG: every change
reflected, nothing standing revoked, the blind vehicle's reports counted as nothing;
the removed sign's landmark is gone from what a vehicle reads (a tombstone reached it).
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fleetsim.evaluation.changes_runs import changes_table

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("changes")
    cmd = [sys.executable, "-m", "hdmap.cli", "eval", "changes", "--quick", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, json.loads((out / "changes.json").read_text())


def test_every_change_is_reflected_and_nothing_standing_is_revoked(quick):
    out, r = quick
    assert (out / "changes.png").stat().st_size > 10_000
    kinds = sorted(e["kind"] for e in r["events"])
    assert kinds == ["add", "move", "remove"]
    for e in r["events"]:
        assert e["passes_to_reflect"] is not None, e
        assert e["waiting_for"] == []
    for key in ("removal_median_passes", "move_median_passes", "addition_median_passes"):
        assert r[key] is not None and r[key] >= 1
    assert r["false_revocations"] == 0 and r["lost"] == {}
    assert r["rogue_revocations"] == 0


def test_the_rogue_reports_everything_and_its_reports_count_for_nothing(quick):
    _, r = quick
    assert r["rogue"]["vehicle"] and r["rogue"]["reported_landmarks"] >= 3
    m = r["services"]["matcher"]
    assert m["revoked"] >= 2  # the removed sign and the moved sign's old place
    assert m["absences_counted"] >= 5
    assert m.get("absences_blind", 0) + m.get("absences_held", 0) > 0
    ingest = r["services"]["ingest"]
    assert ingest["absences_accepted"] > m["absences_counted"]


def test_the_demo_table_has_one_line_per_change(quick):
    _, r = quick
    lines = changes_table(r).splitlines()
    assert len(lines) == 2 + len(r["events"])
    assert [ln.split()[0] for ln in lines[1:-1]] == [
        {"add": "addition", "move": "move", "remove": "removal"}[e["kind"]] for e in r["events"]
    ]
    assert lines[-1].startswith("false revocations 0, by the blind vehicle 0")


def test_the_published_existence_is_calibrated_enough_to_trust(quick):
    _, r = quick
    cal = r["calibration"]
    assert cal["n"] > 100 and cal["brier"] < 0.1
    top = [b for b in cal["bins"] if b["p_lo"] >= 0.95]
    assert top and top[0]["stood"] > 0.9
