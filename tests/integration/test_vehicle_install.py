"""A vehicle install: ``pip install hdmap`` without extras, into a fresh virtual
environment, gives a working onboard side and none of the server or simulation packages.

Installs from a copy of the files git tracks or would track (the build writes nothing into
the checkout); needs the package index the Makefile's own install uses.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]

SMOKE = """
import importlib.util, sys
import numpy as np
from vehicle.agent import VehicleAgent
from vehicle.mapclient import MapClient
from vehicle.config import load_vehicle_model
assert load_vehicle_model() is not None  # the packaged default_vehicle.toml
from vehicle.tracking import smooth_track
assert smooth_track(np.arange(20.0).reshape(10, 2), 5).shape == (10, 2)
missing = [m for m in ("scipy", "matplotlib", "cryptography", "psutil")
           if importlib.util.find_spec(m) is not None]
print("installed:", missing)
sys.exit(1 if missing else 0)
"""


def test_vehicle_install_has_the_onboard_side_and_no_server_packages(tmp_path):
    src = tmp_path / "src"
    files = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    for f in files:
        if (ROOT / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, src / f)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    r = subprocess.run(
        [str(py), "-m", "pip", "install", "--quiet", str(src)],
        capture_output=True,
        text=True,
        timeout=480,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    r = subprocess.run(
        [str(py), "-c", SMOKE], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert r.returncode == 0, r.stdout + r.stderr
    # the CLI says which extra a subcommand needs instead of a traceback
    r = subprocess.run(
        [str(venv / "bin" / "hdmap"), "demo"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 2 and "hdmap[sim]" in r.stderr, r.stderr
    r = subprocess.run(
        [str(venv / "bin" / "hdmap"), "--help"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0 and "loadtest" in r.stdout, r.stderr
