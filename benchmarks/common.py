"""What every benchmark script shares: the machine it ran on, and writing its JSON."""

from __future__ import annotations

import json
import os
import platform
from importlib import metadata
from pathlib import Path


def machine() -> dict[str, str | int]:
    """CPU model, cores and library versions (every benchmark's JSON carries it)."""
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = {}
    for dist in ("numpy", "scipy", "eclipse-zenoh", "msgpack"):
        try:
            versions[dist.removeprefix("eclipse-")] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist.removeprefix("eclipse-")] = "missing"
    try:
        load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        load = "unknown"
    return {
        "cpu": cpu,
        "cores": os.cpu_count() or 0,
        "python": platform.python_version(),
        **versions,
        "platform": platform.platform(),
        "loadavg_at_start": load,
    }


def machine_line(m: dict) -> str:
    return (
        f"machine: {m['cpu']}, {m['cores']} cores; Python {m['python']}, numpy {m['numpy']}, "
        f"scipy {m['scipy']}, zenoh {m['zenoh']}; load average at start {m['loadavg_at_start']}"
    )


def write_json(path: Path | None, report: dict) -> None:
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {path}", flush=True)
