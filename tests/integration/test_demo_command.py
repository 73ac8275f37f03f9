"""``hdmap demo`` end to end on a small town: both noise models, a real stack each."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from hdmap.cli import demo

pytestmark = pytest.mark.timeout(240)


def test_demo_runs_paper_then_fleet_noise_and_writes_both(tmp_path: Path, capsys) -> None:
    out = tmp_path / "demo"
    args = argparse.Namespace(
        out=out, rounds=2, vehicles=8, noise="both", signs=12, seed=0, no_changes=True
    )  # the changes part is the quick changes evaluation (tests/integration/test_changes_eval.py)
    assert demo.run(args) == 0
    text = capsys.readouterr().out
    assert "paper noise" in text and "fleet noise" in text
    assert "final rows side by side" in text
    for d, noise in ((out, "paper"), (out / "fleet", "fleet")):
        for name in ("map.png", "convergence.png"):
            assert (d / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        doc = json.loads((d / "demo.json").read_text())
        assert doc["noise"] == noise
        assert [r["passes"] for r in doc["rounds"]] == [8, 16]
        geo = json.loads((d / "map.geojson").read_text())
        kinds = [f["properties"]["kind"] for f in geo["features"]]
        assert kinds.count("true_sign") == 12
        # the fleet saw signs and the map holds landmarks after 16 passes
        assert doc["rounds"][-1]["observations"] > 0
        assert kinds.count("landmark") > 0
