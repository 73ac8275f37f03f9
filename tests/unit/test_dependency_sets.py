"""The onboard side's dependency set: it imports, and works, without the server and
simulation packages, and every third-party package it needs is a base dependency.

A subprocess blocks scipy, matplotlib, cryptography and psutil at import time, imports
every module of ``vehicle`` and runs the code paths that once used scipy (trajectory
smoothing, per-image assignment). The fresh-install check is in
``tests/integration/test_vehicle_install.py``.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SERVER_ONLY = ("scipy", "matplotlib", "cryptography", "psutil")

PROBE = r"""
import importlib, importlib.abc, importlib.metadata, json, pkgutil, re, sys

def _name(req):
    return re.split(r"[<>=!~;\[ (]", req, maxsplit=1)[0].lower().replace("_", "-")

BLOCKED = set(sys.argv[1].split(","))
BEFORE = {n.split(".")[0] for n in sys.modules}  # loaded by the interpreter's start-up

class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{name} is not part of the onboard install")

sys.meta_path.insert(0, Block())
import numpy as np
import vehicle
for m in pkgutil.walk_packages(vehicle.__path__, "vehicle."):
    importlib.import_module(m.name)
from vehicle.tracking import smooth_track
from hdmap.mapping.association import assign_per_image
assert smooth_track(np.arange(20.0).reshape(10, 2) ** 2, 5).shape == (10, 2)
# two rays of one image whose best landmark is the same: the assignment solver runs
out = assign_per_image(2, np.array([0, 0]), np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]),
                       np.array([1.0, 2.0, 0.5, 5.0]), 10.0)
assert out.tolist() == [1, 0], out
ours = {"hdmap", "schemas", "services", "vehicle", "fleetsim"}
top = {n.split(".")[0] for n in sys.modules} - BEFORE - ours - set(sys.stdlib_module_names)
dists = importlib.metadata.packages_distributions()
print(json.dumps(sorted({d for n in top for d in dists.get(n, [])})))
base = json.loads(sys.argv[2])
closure, todo = set(), list(base)
while todo:  # the base dependencies and what they require in turn
    name = todo.pop()
    if name in closure:
        continue
    closure.add(name)
    try:
        reqs = importlib.metadata.requires(name) or []
    except importlib.metadata.PackageNotFoundError:
        continue
    for req in reqs:
        if "extra ==" not in req:
            todo.append(_name(req))
print(json.dumps(sorted(closure)))
"""


def _base_dependencies() -> set[str]:
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    return {re.split(r"[<>=!~;\[ (]", d, maxsplit=1)[0].lower().replace("_", "-") for d in deps}


def test_onboard_side_imports_and_runs_without_the_server_packages():
    base = _base_dependencies()
    r = subprocess.run(
        [sys.executable, "-c", PROBE, ",".join(SERVER_ONLY), json.dumps(sorted(base))],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    used = {d.lower().replace("_", "-") for d in json.loads(lines[-2])}
    allowed = set(json.loads(lines[-1]))
    assert {"numpy", "eclipse-zenoh", "pyproj"} <= used, used
    assert used <= allowed, f"onboard imports {sorted(used - allowed)}: not base dependencies"
    assert not allowed & set(SERVER_ONLY), "a base dependency pulls in a server package"


def test_server_packages_are_not_base_dependencies():
    assert not _base_dependencies() & set(SERVER_ONLY)
