"""Codec throughput: columnar msgpack messages vs plain msgpack of per-observation dicts.

Measures, in one process and one run (so the ratios are side by side on the same
machine state):

- ObservationBatch of 1,000 observations: encode, strict decode, partial decode
  (all rows good, and with 1% bad rows so the per-row rejection path runs);
- MapDelta with 100 and 1,000 landmarks: encode and decode;
- reference: ``msgpack.packb`` / ``msgpack.unpackb`` of a list of 1,000 dicts with
  the same fields (no validation, no numpy), i.e. the naive row-wise encoding.

Each case is timed timeit-style (``Timer.autorange`` picks the loop count, then
``--repeat`` runs, default 9) and the median per call is reported as rows/s and
MB/s of encoded message. Usage::

    .venv/bin/python benchmarks/bench_codec.py [--repeat 9] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
import timeit
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hdmap.signs import CATALOG
from schemas import Landmarks, MapDelta, ObservationBatch, Observations, Removals

T0 = 1.7e9
REFERENCE = "reference: msgpack list of 1000 dicts"


def make_obs(n: int, seed: int = 0) -> Observations:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3)) * [1.0, 1.0, 0.1]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rng_m = np.where(rng.random(n) < 0.3, 0.0, rng.uniform(5.0, 80.0, n))
    return Observations(
        obs_id=np.arange(n, dtype=np.uint64) + 1_000_000,
        t=T0 + np.sort(rng.uniform(0, 600, n)),
        image=np.sort(rng.integers(0, 20_000, n)).astype(np.uint32),
        sign_class=rng.choice(CATALOG.codes, n).astype(np.uint16),
        lat=60.17 + rng.normal(0, 0.01, n),
        lon=24.94 + rng.normal(0, 0.01, n),
        h=rng.uniform(10, 40, n),
        direction=d,
        sigma_az=rng.uniform(0.002, 0.05, n),
        sigma_el=rng.uniform(0.002, 0.02, n),
        sigma_pos_h=rng.uniform(0.5, 10, n),
        sigma_pos_v=rng.uniform(1, 15, n),
        range_m=rng_m,
        sigma_range_m=rng_m * 0.12,
        score=rng.uniform(0, 1, n).astype(np.float32),
    )


def make_landmarks(n: int, seed: int = 1) -> Landmarks:
    rng = np.random.default_rng(seed)
    cov = np.tile([1.0, 0.1, 0.0, 1.2, 0.0, 4.0], (n, 1)) * rng.uniform(0.5, 2, (n, 1))
    return Landmarks(
        id=np.arange(n, dtype=np.uint64) + 1,
        sign_class=rng.choice(CATALOG.codes, n).astype(np.uint16),
        lat=60.17 + rng.normal(0, 0.01, n),
        lon=24.94 + rng.normal(0, 0.01, n),
        h=rng.uniform(10, 40, n),
        cov=cov,
        status=np.ones(n, np.uint8),
        n_obs=rng.integers(1, 10_000, n).astype(np.uint32),
        n_passes=rng.integers(1, 500, n).astype(np.uint32),
        revision=rng.integers(1, 2**40, n).astype(np.uint64),
        updated_at=T0 + rng.uniform(0, 1e5, n),
        source_time=T0 + rng.uniform(0, 1e5, n),
    )


def obs_dicts(obs: Observations) -> list[dict]:
    """The same observations as one msgpack-native dict per row (the naive encoding)."""
    cols = {name: getattr(obs, name).tolist() for name, _ in Observations.CODEC.cols}
    return [{k: v[i] for k, v in cols.items()} for i in range(len(obs))]


def machine() -> dict[str, str | int]:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count() or 0,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "msgpack": ".".join(map(str, msgpack.version)),
        "platform": platform.platform(),
    }


def measure(fn: Callable[[], object], repeat: int) -> tuple[float, int]:
    """Median seconds per call over ``repeat`` runs of an autoranged loop."""
    timer = timeit.Timer(fn)
    number, _ = timer.autorange()
    times = timer.repeat(repeat=repeat, number=number)
    return statistics.median(times) / number, number


def cases() -> list[tuple[str, str, int, int, Callable[[], object]]]:
    """(message, operation, rows, message bytes, function)."""
    out = []

    def add(group: str, op: str, rows: int, data: bytes, fn: Callable[[], object]) -> None:
        out.append((group, op, rows, len(data), fn))

    obs = make_obs(1000)
    batch = ObservationBatch("veh-0042", 7, 1, T0, obs)
    data = batch.to_bytes()
    group = "ObservationBatch 1000 obs"
    add(group, "encode", 1000, data, batch.to_bytes)
    add(group, "decode strict", 1000, data, lambda: ObservationBatch.from_bytes(data))
    add(group, "decode partial", 1000, data, lambda: ObservationBatch.from_bytes_partial(data))
    bad = make_obs(1000)
    bad.lat[::100] = np.nan  # 1% bad rows: the per-row rejection path
    bad_data = ObservationBatch("veh-0042", 7, 1, T0, bad).to_bytes()
    assert len(ObservationBatch.from_bytes_partial(bad_data)[1]) == 10
    add(
        group,
        "decode partial, 1% bad",
        1000,
        bad_data,
        lambda: ObservationBatch.from_bytes_partial(bad_data),
    )

    no_removals = Removals(id=np.zeros(0, np.uint64), revision=np.zeros(0, np.uint64))
    for n in (100, 1000):
        delta = MapDelta("1201202110133102", 41, 42, T0, make_landmarks(n), no_removals)
        ddata = delta.to_bytes()
        add(f"MapDelta {n} landmarks", "encode", n, ddata, delta.to_bytes)
        add(f"MapDelta {n} landmarks", "decode", n, ddata, lambda d=ddata: MapDelta.from_bytes(d))

    rows = obs_dicts(obs)
    ref = msgpack.packb(rows, use_bin_type=True)
    assert msgpack.unpackb(ref) == rows
    add(REFERENCE, "encode", 1000, ref, lambda: msgpack.packb(rows, use_bin_type=True))
    add(REFERENCE, "decode", 1000, ref, lambda: msgpack.unpackb(ref, raw=False))
    return out


def run(repeat: int = 9) -> dict:
    results = []
    for group, op, rows, nbytes, fn in cases():
        fn()  # warm up
        sec, number = measure(fn, repeat)
        results.append(
            dict(
                message=group,
                operation=op,
                rows=rows,
                bytes=nbytes,
                us_per_call=sec * 1e6,
                rows_per_s=rows / sec,
                mb_per_s=nbytes / sec / 1e6,
                loops=number,
                repeat=repeat,
            )
        )
    when = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return {"machine": machine(), "when": when, "results": results}


def ratios(results: list[dict]) -> list[str]:
    """Columnar vs reference, same run."""
    by = {(r["message"], r["operation"]): r for r in results}
    lines = []
    pairs = [("encode", "encode"), ("decode strict", "decode"), ("decode partial", "decode")]
    for op, ref_op in pairs:
        a, b = by[("ObservationBatch 1000 obs", op)], by[(REFERENCE, ref_op)]
        lines.append(
            f"ObservationBatch {op} is {b['us_per_call'] / a['us_per_call']:.1f}x "
            f"the speed of msgpack dicts {ref_op}; size "
            f"{a['bytes'] / b['bytes']:.2f}x"
        )
    return lines


def table(report: dict) -> str:
    m = report["machine"]
    head = [
        f"machine: {m['cpu']}, {m['cores']} cores; Python {m['python']}, numpy {m['numpy']}, "
        f"msgpack {m['msgpack']}",
        f"median of {report['results'][0]['repeat']} runs (timeit autorange loops)",
        "",
        f"| {'message':<38} | {'operation':<22} | {'bytes':>8} | {'us/call':>9} "
        f"| {'rows/s':>11} | {'MB/s':>7} |",
        f"|{'-' * 40}|{'-' * 24}|{'-' * 10}|{'-' * 11}|{'-' * 13}|{'-' * 9}|",
    ]
    body = [
        f"| {r['message']:<38} | {r['operation']:<22} | {r['bytes']:>8} | "
        f"{r['us_per_call']:>9.1f} | {r['rows_per_s']:>11,.0f} | {r['mb_per_s']:>7.1f} |"
        for r in report["results"]
    ]
    return "\n".join([*head, *body, "", *ratios(report["results"])])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=9, help="timed runs per case (median; >= 7)")
    ap.add_argument("--json", type=Path, help="also write the results as JSON to this file")
    args = ap.parse_args(argv)
    if args.repeat < 7:
        ap.error("--repeat must be at least 7")
    report = run(args.repeat)
    print(table(report))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
