"""Codec throughput: columnar msgpack messages vs plain msgpack of per-observation dicts.

Measures, in one process and one run (so the ratios are side by side on the same
machine state):

- ObservationBatch of 1,000 observations: encode, strict decode, partial decode
  (all rows good, and with 1% bad rows so the per-row rejection path runs);
- MapDelta (publisher -> vehicles) with 10, 100 and 1,000 upserted landmarks, and one
  with 1,000 upserts plus 100 removals: encode and decode;
- MapSnapshot (the ``hdmap/v1/map/<tile>`` reply) of 100, 1,000 and 10,000 landmarks:
  encode and decode;
- references: ``msgpack.packb`` / ``msgpack.unpackb`` of a list of 1,000 dicts with
  the same fields (no validation, no numpy), i.e. the naive row-wise encoding, for
  observations and for landmarks.

Each case is timed timeit-style (``Timer.autorange`` picks the loop count, then
``--repeat`` runs, default 9) and the median per call is reported as rows/s and
MB/s of encoded message. ``--quick`` uses 3 runs of about 20 ms each. Usage::

    .venv/bin/python benchmarks/bench_codec.py [--quick] [--repeat 9] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import timeit
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine
from hdmap.geo.signs import CATALOG
from schemas import Landmarks, MapDelta, MapSnapshot, ObservationBatch, Observations, Removals

T0 = 1.7e9
REFERENCE = "reference: msgpack list of 1000 dicts"
REFERENCE_LM = "reference: msgpack 1000 landmark dicts"
TILE = "1201202110133102"


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


def landmark_dicts(lm: Landmarks) -> list[dict]:
    """The same landmarks as one msgpack-native dict per row (the naive encoding)."""
    cols = {name: getattr(lm, name).tolist() for name, _ in Landmarks.CODEC.cols}
    return [{k: v[i] for k, v in cols.items()} for i in range(len(lm))]


def measure(fn: Callable[[], object], repeat: int, quick: bool = False) -> tuple[float, int]:
    """Median seconds per call over ``repeat`` runs of an autoranged loop (``quick``: loops
    of about 20 ms instead of autorange's 0.2 s)."""
    timer = timeit.Timer(fn)
    if quick:
        one = timer.timeit(1)
        number = max(1, int(0.02 / max(one, 1e-7)))
    else:
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
    for n in (10, 100, 1000):
        delta = MapDelta(TILE, 41, 42, T0, make_landmarks(n), no_removals)
        ddata = delta.to_bytes()
        add(f"MapDelta {n} landmarks", "encode", n, ddata, delta.to_bytes)
        add(f"MapDelta {n} landmarks", "decode", n, ddata, lambda d=ddata: MapDelta.from_bytes(d))
    removals = Removals(
        id=np.arange(100, dtype=np.uint64) + 5_000_000, revision=np.full(100, 7, np.uint64)
    )
    delta = MapDelta(TILE, 41, 42, T0, make_landmarks(1000), removals)
    ddata = delta.to_bytes()
    group = "MapDelta 1000 landmarks + 100 removed"
    add(group, "encode", 1100, ddata, delta.to_bytes)
    add(group, "decode", 1100, ddata, lambda d=ddata: MapDelta.from_bytes(d))

    for n in (100, 1000, 10_000):
        snap = MapSnapshot(TILE, 42, make_landmarks(n, seed=2))
        sdata = snap.to_bytes()
        add(f"MapSnapshot {n} landmarks", "encode", n, sdata, snap.to_bytes)
        add(
            f"MapSnapshot {n} landmarks",
            "decode",
            n,
            sdata,
            lambda d=sdata: MapSnapshot.from_bytes(d),
        )

    rows = obs_dicts(obs)
    ref = msgpack.packb(rows, use_bin_type=True)
    assert msgpack.unpackb(ref) == rows
    add(REFERENCE, "encode", 1000, ref, lambda: msgpack.packb(rows, use_bin_type=True))
    add(REFERENCE, "decode", 1000, ref, lambda: msgpack.unpackb(ref, raw=False))
    lm_rows = landmark_dicts(make_landmarks(1000))
    lm_ref = msgpack.packb(lm_rows, use_bin_type=True)
    assert msgpack.unpackb(lm_ref) == lm_rows
    add(REFERENCE_LM, "encode", 1000, lm_ref, lambda: msgpack.packb(lm_rows, use_bin_type=True))
    add(REFERENCE_LM, "decode", 1000, lm_ref, lambda: msgpack.unpackb(lm_ref, raw=False))
    return out


def run(repeat: int = 9, quick: bool = False) -> dict:
    results = []
    for group, op, rows, nbytes, fn in cases():
        fn()  # warm up
        sec, number = measure(fn, repeat, quick)
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
    return {
        "benchmark": "codec",
        "machine": machine(),
        "when": when,
        "quick": quick,
        "results": results,
        "ratios": ratios(results),
    }


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
    for op in ("encode", "decode"):
        a, b = by[("MapDelta 1000 landmarks", op)], by[(REFERENCE_LM, op)]
        lines.append(
            f"MapDelta 1000 landmarks {op} is {b['us_per_call'] / a['us_per_call']:.1f}x "
            f"the speed of msgpack landmark dicts {op}; size {a['bytes'] / b['bytes']:.2f}x"
        )
    return lines


def table(report: dict) -> str:
    m = report["machine"]
    head = [
        f"machine: {m['cpu']}, {m['cores']} cores; Python {m['python']}, numpy {m['numpy']}, "
        f"msgpack {m['msgpack']}, zenoh {m.get('zenoh', '?')}; "
        f"load average at start {m.get('loadavg_at_start', '?')}",
        f"median of {report['results'][0]['repeat']} runs "
        f"({'~20 ms loops, --quick' if report.get('quick') else 'timeit autorange loops'})",
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
    ap.add_argument("--repeat", type=int, help="timed runs per case (median; >= 7, default 9)")
    ap.add_argument("--quick", action="store_true", help="3 runs of ~20 ms loops (smoke test)")
    ap.add_argument("--json", type=Path, help="also write the results as JSON to this file")
    args = ap.parse_args(argv)
    repeat = args.repeat or (3 if args.quick else 9)
    if repeat < 7 and not args.quick:
        ap.error("--repeat must be at least 7")
    report = run(repeat, args.quick)
    print(table(report))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
