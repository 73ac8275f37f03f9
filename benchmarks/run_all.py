"""Run every benchmark script (``benchmarks/bench_*.py``) in sequence, one at a time.

Each script runs as its own process with ``--json out/bench/<name>.json`` (``<name>`` is
the file name without ``bench_``); its console output goes to ``out/bench/<name>.log``.
One progress line per script; a summary (status, seconds, files) is written to
``out/bench/summary.json``. ``--quick`` passes ``--quick`` to the scripts that accept it
(``bench_zenoh.py`` gets ``--seconds 1 --threads 1 4`` instead). Exit status 1 if a
script failed.

    .venv/bin/python benchmarks/run_all.py [--quick] [--out out/bench] [--only solver scale]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

QUICK_ARGS = {"zenoh": ["--seconds", "1", "--threads", "1", "4"]}
"""Quick arguments of scripts without a ``--quick`` flag."""


def name_of(script: Path) -> str:
    return script.stem.removeprefix("bench_")


def accepts_quick(script: Path) -> bool:
    try:
        out = subprocess.run(
            [sys.executable, str(script), "--help"],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=ROOT,
        )
    except subprocess.TimeoutExpired:
        return False
    return "--quick" in out.stdout


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes everywhere")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="e.g. solver scale codec")
    ap.add_argument("--skip", nargs="+", metavar="NAME", default=[])
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per script")
    args = ap.parse_args(argv)
    scripts = sorted(HERE.glob("bench_*.py"))
    if args.only:
        scripts = [s for s in scripts if name_of(s) in args.only]
    scripts = [s for s in scripts if name_of(s) not in args.skip]
    if not scripts:
        ap.error("no benchmark script selected")
    args.out.mkdir(parents=True, exist_ok=True)
    from bench_solver import machine, machine_line

    summary: dict = {
        "machine": machine(),
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "quick": args.quick,
        "scripts": [],
    }
    print(machine_line(summary["machine"]), flush=True)
    failed = 0
    for i, script in enumerate(scripts, 1):
        name = name_of(script)
        json_path = args.out / f"{name}.json"
        log_path = args.out / f"{name}.log"
        json_path.unlink(missing_ok=True)  # a stale file must not pass for this run's
        cmd = [sys.executable, str(script), "--json", str(json_path)]
        if args.quick:
            cmd += ["--quick"] if accepts_quick(script) else QUICK_ARGS.get(name, [])
        print(f"[{i}/{len(scripts)}] {script.name} ...", end=" ", flush=True)
        t0 = time.perf_counter()
        with open(log_path, "w") as log:
            log.write("$ " + " ".join(cmd) + "\n")
            log.flush()
            try:
                rc = subprocess.run(
                    cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, timeout=args.timeout
                ).returncode
            except subprocess.TimeoutExpired:
                rc = -1
        dt = time.perf_counter() - t0
        ok = rc == 0 and json_path.exists()
        failed += not ok
        status = "ok" if ok else f"FAILED (exit {rc}), see {log_path}"
        print(f"{status} in {dt:.1f} s -> {json_path if ok else log_path}", flush=True)
        summary["scripts"].append(
            {
                "script": script.name,
                "command": cmd,
                "ok": ok,
                "exit": rc,
                "seconds": dt,
                "json": str(json_path),
                "log": str(log_path),
            }
        )
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"{len(scripts) - failed}/{len(scripts)} ok; summary in {args.out / 'summary.json'}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
