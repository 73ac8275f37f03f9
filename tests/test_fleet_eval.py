"""``hdmap eval fleet --quick``: the real pipeline on a part of central Helsinki, end to end.

Runs as a subprocess (router and services are its own subprocesses, stopped by it), then
checks the JSON: documented keys, counts that add up, and numbers in sane ranges (fixed
seed; ranges, not exact values). Also the pure scoring helpers on hand-made cases.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from fleetsim.world import straight_road
from hdmap.evaluation.fleet_eval import EvalState, ObsKeys, SignRecord, bin_table, targets

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet")
    cmd = [sys.executable, "-m", "hdmap.cli", "eval", "fleet", "--quick", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, json.loads((out / "fleet.json").read_text()), proc.stderr


def test_quick_run_writes_json_figures_and_a_table(quick):
    out, d, stderr = quick
    assert {
        "meta",
        "rounds",
        "by_passes",
        "observations",
        "services",
        "targets_at_50_passes",
    } <= set(d)
    for name in d["meta"]["figures"]:
        assert (out / name).stat().st_size > 10_000
    assert "passes signs recall" in stderr
    assert d["meta"]["signs"] >= 100 and d["meta"]["classes"] >= 10
    row_keys = {
        "passes_lo",
        "signs",
        "recall",
        "precision",
        "duplicated",
        "mean_err_m",
        "p95_err_m",
        "coverage95",
        "assoc_right",
        "assoc_unlinked",
    }
    assert all(row_keys <= set(r) for r in d["by_passes"])


def test_quick_run_counts_add_up_and_the_map_is_sane(quick):
    _, d, _ = quick
    s = d["services"]
    # every accepted observation reached the matcher and was linked or is pending
    assert s["ingest"]["accepted"] == d["observations"]["uploaded"]
    assert s["matcher"]["received"] == s["ingest"]["accepted"]
    m = s["matcher"]
    kept = m["linked"] + m["pending"] + m.get("expired", 0)
    assert m["received"] == kept + m.get("track_discarded", 0)
    assert s["solver"]["observations"] == m["linked"]
    assert d["observations"]["linked"] == m["linked"]  # the replayed association log
    assert all(r["quiet"] for r in d["rounds"])
    last = d["rounds"][-1]
    assert last["recall"] > 0.6 and 0.5 < last["mean_err_m"] < 4.0
    busy = [r for r in d["by_passes"] if r["passes_lo"] >= 10]
    assert busy and all(r["assoc_right"] > 0.6 for r in busy)


def test_bin_table_counts_each_sign_once_per_bin_with_its_last_state():
    world = straight_road()
    rec = [
        SignRecord(
            np.array([1]),
            np.array([True]),
            np.array([3.0]),
            np.array([True]),
            np.array([7], np.uint64),
        ),
        SignRecord(
            np.array([2]),
            np.array([True]),
            np.array([2.0]),
            np.array([False]),
            np.array([7], np.uint64),
        ),
    ]
    truth = [ObsKeys("v", np.array([1, 2, 3]), np.array([0, 0, -1]))]  # obs 3: false positive
    state = EvalState(world, records=rec, truth=truth)
    links = [ObsKeys("v", np.array([1, 2, 3]), np.array([7, 8, 7]))]
    lm_rows = [{"lo": lo, "n": 1, "paired": 1, "dup": 0} for lo in (1, 2)]
    table = bin_table(state, lm_rows, links, bins=(1, 2))
    assert [r["passes_lo"] for r in table] == [1, 2]
    assert table[0]["mean_err_m"] == 3.0 and table[0]["coverage95"] == 1.0
    assert table[1]["mean_err_m"] == 2.0 and table[1]["coverage95"] == 0.0
    # of the sign's two observations one went to its landmark (7), one elsewhere (8)
    assert table[1]["assoc_right"] == 0.5 and table[1]["assoc_unpaired_landmark"] == 0.5
    assert targets(table) == {"evaluated": False}
