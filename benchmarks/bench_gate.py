"""Gating statistic kernel: the projected covariance ``J C J^T`` by batched matmul vs einsum.

:func:`hdmap.mapping.association.pair_chi2` is the matcher's hottest function (5.5 of 19.6 s
under cProfile replaying a fleet evaluation's uploads, before this change) and also runs
in the vehicle's tracker and in initiation. Per (ray, landmark) pair it projects the 3x3
position covariance (landmark plus ray origin) through the 2x3 angle Jacobian and takes
the covariance along the ray.
This script times, side by side in one run and on the same random pairs:

- ``einsum3``: ``np.einsum("kij,kjl,kml->kim", J, C, J)`` (the alternative:
  a three-operand einsum without a contraction path, a nested loop in C);
- ``matmul``: ``J @ C @ J^T`` (the form used now), checked equal to 1e-12 relative;
- the whole ``pair_chi2`` at the same sizes (now), and what it took with ``einsum3``
  (estimated: now plus the kernel's difference).

(The along-ray quadratic form ``d^T C d`` stays an einsum: as a matmul it was no faster,
0.83-1.00x at 50-2,000 pairs.)

at ``--pairs`` pairs per call (the matcher's calls hold tens to thousands). Figures are
microseconds per call, the median of ``--repeat`` timings of ``--number`` calls.

    .venv/bin/python benchmarks/bench_gate.py [--quick] [--json out/bench/gate.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import timeit
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, machine_line, write_json
from hdmap.mapping.association import GateConfig, LocalRays, origin_cov, pair_chi2
from hdmap.mapping.estimator.gating import angle_jacobian


def random_pairs(rng: np.random.Generator, k: int) -> tuple[LocalRays, np.ndarray, np.ndarray]:
    """``k`` rays 10-60 m before landmarks near their line of sight, and the landmarks'
    positions and covariances (1-3 m per axis)."""
    origin = rng.normal(0.0, 50.0, (k, 3))
    x = origin + np.c_[rng.uniform(10, 60, k), rng.normal(0, 5, k), rng.normal(1, 0.5, k)]
    d = x - origin + rng.normal(0, 0.5, (k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = LocalRays(
        origin=origin,
        direction=d,
        sigma_az=np.full(k, 0.003),
        sigma_el=np.full(k, 0.003),
        sigma_pos_h=np.full(k, 1.0),
        sigma_pos_v=np.full(k, 1.5),
        range_m=np.linalg.norm(x - origin, axis=1) * rng.uniform(0.8, 1.2, k),
        sigma_range_m=np.full(k, 5.0),
        image=np.arange(k, dtype=np.int64),
        sign_class=np.zeros(k, np.int64),
    )
    s = rng.uniform(1.0, 3.0, (k, 3))
    cov = np.zeros((k, 3, 3))
    cov[:, [0, 1, 2], [0, 1, 2]] = s**2
    return rays, x, cov


def per_call_us(fn: Callable[[], object], number: int, repeat: int) -> float:
    return statistics.median(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6


def measure(rng: np.random.Generator, k: int, number: int, repeat: int) -> dict:
    """Both kernels and ``pair_chi2`` at ``k`` pairs (microseconds per call)."""
    rays, x, cov = random_pairs(rng, k)
    ri = np.arange(k)
    a_cov = origin_cov(rays, 2.5, 3.5)
    c = cov + a_cov
    j = angle_jacobian(x - rays.origin)
    old = np.einsum("kij,kjl,kml->kim", j, c, j)
    new = j @ c @ j.transpose(0, 2, 1)
    if not np.allclose(new, old, rtol=0.0, atol=1e-12 * np.abs(old).max()):
        raise SystemExit(f"J C J^T differs at {k} pairs")
    gate = GateConfig()
    t = {
        "pairs": k,
        "einsum3_us": per_call_us(lambda: np.einsum("kij,kjl,kml->kim", j, c, j), number, repeat),
        "matmul_us": per_call_us(lambda: j @ c @ j.transpose(0, 2, 1), number, repeat),
        "pair_chi2_us": per_call_us(
            lambda: pair_chi2(rays, ri, x, cov, a_cov, gate), number, repeat
        ),
    }
    t["kernel_speedup"] = t["einsum3_us"] / t["matmul_us"]
    t["pair_chi2_before_us_est"] = t["pair_chi2_us"] + t["einsum3_us"] - t["matmul_us"]
    return t


def run(pairs: list[int], number: int, repeat: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [measure(rng, k, number, repeat) for k in pairs]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, nargs="+", default=[50, 300, 2000])
    p.add_argument("--number", type=int, default=300)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--quick", action="store_true", help="fewer timings (for run_all --quick)")
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    number, repeat = (30, 3) if a.quick else (a.number, a.repeat)
    m = machine()
    print(machine_line(m), flush=True)
    rows = run(a.pairs, number, repeat)
    print(
        f"{'pairs':>6} {'JCJ einsum3':>12} {'JCJ matmul':>11} {'x':>5} {'pair_chi2':>10} "
        f"{'before (est.)':>14}"
    )
    for r in rows:
        print(
            f"{r['pairs']:6d} {r['einsum3_us']:10.1f}us {r['matmul_us']:9.1f}us "
            f"{r['kernel_speedup']:5.2f} {r['pair_chi2_us']:8.1f}us "
            f"{r['pair_chi2_before_us_est']:12.1f}us"
        )
    write_json(a.json, {"machine": m, "number": number, "repeat": repeat, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
