"""``hdmap calibrate-gnss``: the floor of a fix-minus-truth log as a services config line
the solver accepts, equal to what the fleet evaluation gives the solver on the same log."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np

from fleetsim.evaluation.fleet_eval import gsdc_floor
from fleetsim.gnss_replay import DATA
from hdmap.cli import main
from hdmap.mapping.gnss_floor import floor_enu
from hdmap.runtime.config import from_mapping
from services.solver.service import SolverConfig


def test_the_printed_line_configures_the_solver_with_the_evaluations_floor(tmp_path, capsys):
    out = tmp_path / "floor.json"
    assert main(["calibrate-gnss", "--errors", str(DATA), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    table = tomllib.loads(text[text.index("[solver]") :])
    cfg = from_mapping(SolverConfig, table["solver"], "solver")
    np.testing.assert_allclose(cfg.shared_floor(), floor_enu(gsdc_floor()), atol=1e-5)
    art = json.loads(out.read_text())
    assert len(art["drives"]) == 2 and art["batches"] == [6, 6]


def test_a_log_without_the_columns_is_refused_naming_them(tmp_path: Path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("trace,t_s,east\nd,0,1\n")
    assert main(["calibrate-gnss", "--errors", str(bad)]) == 2
    assert "missing column(s) err_east_m, err_north_m" in capsys.readouterr().err
