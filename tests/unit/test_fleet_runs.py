"""The separate seed runs of ``hdmap eval fleet --seeds``: a run is stopped when its log has
not grown for ``SEED_STALL_TIMEOUT_S`` or it is past its limit per pass, not at a fixed
time (1,200-pass runs on a busy machine took longer than 30 minutes with nothing wrong)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from fleetsim.evaluation.fleet_runs import SEED_STALL_TIMEOUT_S, SeedRunError, _check_alive


def test_a_run_is_stopped_when_its_log_is_quiet_or_it_is_past_its_limit(tmp_path: Path):
    log = tmp_path / "seed-3.log"
    log.write_text("round 1/4: ...\n")
    now = time.monotonic()
    long_ago = now - 2 * SEED_STALL_TIMEOUT_S
    _check_alive(3, log, long_ago, 10 * SEED_STALL_TIMEOUT_S)  # busy for an hour, still writing
    os.utime(log, (time.time() - 2 * SEED_STALL_TIMEOUT_S,) * 2)
    with pytest.raises(SeedRunError, match=r"seed 3: its log .* has not grown"):
        _check_alive(3, log, long_ago, 10 * SEED_STALL_TIMEOUT_S)
    _check_alive(3, log, now, 10 * SEED_STALL_TIMEOUT_S)  # just started: a quiet log is fine
    with pytest.raises(SeedRunError, match=r"seed 3: no result after 100 s"):
        _check_alive(3, log, now - 200.0, 100.0)
