"""``hdmap eval localize --quick``: a vehicle localised against the map its fleet built
(issue 22 point 1), end to end through the command: the map built in-process (40 passes of
six vehicles through the matcher and the solver on SQLite), three held-out passes
localised every second. Checks the JSON's keys and sanity, and the PNG (about 15 s)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration

KEYS = (
    "gnss_p50_m",
    "gnss_p95_m",
    "map_aided_p50_m",
    "map_aided_p95_m",
    "coverage95",
    "map_aided_share",
    "map_aided_share_all",
    "map_frame_p50_m",
    "condition",
    "targets",
    "targets_met",
    "per_seed",
)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("localize")
    cmd = [sys.executable, "-m", "hdmap.cli", "eval", "localize", "--quick", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, json.loads((out / "localize.json").read_text())


def test_the_report_has_its_keys_and_the_figure(quick):
    out, r = quick
    assert (out / "localize.png").stat().st_size > 20_000
    for key in KEYS:
        assert key in r, key
    assert "3rd distinct mapped sign" in r["condition"]
    seed = r["per_seed"]["0"]
    assert seed["map"]["confirmed"] > 20 and len(seed["passes"]) == 3
    assert r["seconds_after_condition"] > 60


def test_the_map_aided_fix_beats_raw_gnss_and_covers(quick):
    _, r = quick
    assert r["map_aided_share"] > 0.8
    assert r["map_aided_p50_m"] < 0.6 * r["gnss_p50_m"]
    assert 0.8 <= r["coverage95"] <= 1.0
    assert r["matches_right_share"] > 0.95
