"""Solver kernel throughput: incremental sums vs a per-ray loop vs re-solving every pass.

One simulated fleet (``--landmarks`` landmarks, passes of ``--rays-per-pass`` rays, one
round = one pass of every landmark, rays of a round mixed and shuffled in one batch, as
the matcher hands them to the solver) is fed, round by round, to:

- ``incremental``: the solver's kernel, :meth:`LandmarkSums.accumulate` on the round's
  batch, then :meth:`LandmarkSums.solve` of the touched landmarks (the calls the solver
  service makes: ``update_reference=False``, passes closed by eviction only);
- ``per_ray_loop``: the same accumulation one ray at a time (a Python loop calling
  ``accumulate`` with one ray), then the same vectorised solve per round; the results are
  checked to be identical to ``incremental``. Its cost per ray does not grow with the
  rounds, so it runs on the first rounds only (at most ``--loop-max-obs`` rays);
- ``rebuild_ours``: the paper's way of updating with our estimator: at every round, fresh
  sums of every stored ray of the touched landmarks (one vectorised ``accumulate``), then
  the same ``solve`` (isolates incremental vs re-solving; checked equal to 1e-6 m);
- ``paper_batch``: the paper's way, made as fast as we could: at every round, each
  touched landmark is re-optimised over ALL its stored rays by the closed form of the
  paper's eq. (4) (unweighted textbook sums, 3x3 solve, ray-level sandwich covariance;
  numpy, vectorised over landmarks), i.e. O(rays so far) per pass instead of O(rays of
  the pass); checked against the kernel run with ``EstimatorConfig.paper()`` on the same
  rays (same estimate);
- ``paper_lsq``: the paper's way literally: ``scipy.optimize.least_squares`` per landmark
  per pass on the textbook orthogonal-distance residuals of all its stored rays, warm
  started at its previous estimate. Too slow for every landmark: run on the first
  ``--lsq-landmarks`` landmarks (its observations/s is over those landmarks' rays) and
  checked against ``paper_batch`` on the same landmarks.

at 10, 100 and 1,000 observations per landmark (``--obs-per-landmark``). Every method gets
the same rays; every figure is observations ingested (and solved) per second of wall
time, median of ``--repeat`` runs, and the ratios are taken inside one run.

    .venv/bin/python benchmarks/bench_solver.py [--quick] [--json out/bench/solver.json]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, machine_line, write_json
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from hdmap.mapping.estimator.model import SYM_I, SYM_J, ray_angles, sym_to_mat

# ---------------------------------------------------------------------------- shared helpers


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, list[float], object]:
    """Median wall seconds of ``repeat`` calls of ``fn``, all the times, the last result."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out


# ---------------------------------------------------------------------------- the fleet


@dataclass
class Fleet:
    """Rays of ``n`` landmarks, ``passes`` rounds of one pass each, sorted by round."""

    x_true: np.ndarray
    x0: np.ndarray
    rows: np.ndarray
    clusters: np.ndarray
    rays: Rays
    starts: np.ndarray
    """Round r is ``[starts[r], starts[r + 1])``."""

    @property
    def rounds(self) -> int:
        return self.starts.size - 1

    def round_slice(self, r: int) -> slice:
        return slice(int(self.starts[r]), int(self.starts[r + 1]))

    def batch(self, sl: slice) -> tuple[np.ndarray, np.ndarray, Rays]:
        rays = Rays(
            self.rays.origin[sl],
            self.rays.direction[sl],
            self.rays.sigma_az[sl],
            self.rays.sigma_el[sl],
            self.rays.sigma_pos_h[sl],
            self.rays.sigma_pos_v[sl],
        )
        return self.rows[sl], self.clusters[sl], rays


def pass_rays(
    x_true: np.ndarray,
    theta: np.ndarray,
    per_pass: int,
    rng: np.random.Generator,
    sigma_az: float = 0.02,
    sigma_el: float = 0.01,
    sigma_pos: float = 1.0,
) -> tuple[np.ndarray, Rays]:
    """One pass of ``per_pass`` rays toward each sign (road heading ``theta``), images
    40..10 m before it; returns (index into ``x_true`` of each ray, rays), grouped by sign.

    Lateral position in the lane uniform +/-1.5 m, a GNSS bias shared by the pass's images
    (``sigma_pos`` per horizontal axis, half that vertically) plus white origin noise, and
    white angular noise, all reported."""
    n = x_true.shape[0]
    u = np.column_stack([np.sin(theta), np.cos(theta), np.zeros(n)])  # along the road
    r = np.column_stack([np.cos(theta), -np.sin(theta), np.zeros(n)])  # to the right
    dist = np.linspace(40.0, 10.0, per_pass)
    lm = np.repeat(np.arange(n), per_pass)
    k = np.tile(np.arange(per_pass), n)
    lat = rng.uniform(-1.5, 1.5, n)[lm]
    cam = x_true[lm] - (5.0 - lat)[:, None] * r[lm] - dist[k][:, None] * u[lm]
    cam[:, 2] = 1.4
    bias = rng.normal(0.0, sigma_pos, (n, 3))[lm] * [1.0, 1.0, 0.5]
    origin = cam + bias + rng.normal(0.0, 0.5 * sigma_pos, cam.shape)
    az, el = ray_angles(x_true[lm] - cam)
    m = lm.size
    rays = Rays.from_angles(
        origin,
        az + rng.normal(0, sigma_az, m),
        el + rng.normal(0, sigma_el, m),
        sigma_az,
        sigma_el,
        1.12 * sigma_pos,
        0.7 * sigma_pos,
    )
    return lm, rays


def make_signs(n: int, rng: np.random.Generator, extent_m: float = 300.0):
    """(true positions, road headings, initial positions) of ``n`` signs in a tile."""
    x_true = np.column_stack([rng.uniform(-extent_m, extent_m, (n, 2)), rng.uniform(2, 4, n)])
    theta = rng.uniform(0, 2 * np.pi, n)
    x0 = x_true + rng.normal(0, 2.0, x_true.shape) * [1.0, 1.0, 0.3]
    return x_true, theta, x0


def make_fleet(n: int, passes: int, per_pass: int, seed: int = 0) -> Fleet:
    """``passes`` rounds of one pass of every sign each, rays of a round shuffled (mixed
    landmarks, unsorted, as the matcher sends them); one vehicle pass sees 10 signs
    (shared cluster key)."""
    rng = np.random.default_rng(seed)
    x_true, theta, x0 = make_signs(n, rng)
    keys = rng.integers(1, 2**62, size=(passes, (n + 9) // 10))
    parts, clusters = [], []
    for p in range(passes):
        lm, rays = pass_rays(x_true, theta, per_pass, rng)
        order = rng.permutation(lm.size)
        parts.append((lm[order], rays.take(order)))
        clusters.append(keys[p, lm[order] // 10])
    return Fleet(
        x_true=x_true,
        x0=x0,
        rows=np.concatenate([q[0] for q in parts]).astype(np.int64),
        clusters=np.concatenate(clusters).astype(np.int64),
        rays=Rays.concat([q[1] for q in parts]),
        starts=np.arange(passes + 1, dtype=np.int64) * (n * per_pass),
    )


# ---------------------------------------------------------------------------- methods


def load_sums_class(path: Path) -> type:
    """``LandmarkSums`` from another copy of ``hdmap/mapping/estimator/sums.py`` (e.g. ``git show
    REV:hdmap/mapping/estimator/sums.py > /tmp/sums_rev.py``), to time two versions side by side."""
    spec = importlib.util.spec_from_file_location(f"sums_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"cannot load {path}")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.LandmarkSums


def run_incremental(f: Fleet, cfg: EstimatorConfig, cls: type = LandmarkSums) -> np.ndarray:
    s = cls(cfg, capacity=f.x0.shape[0])
    s.new_rows(f.x0.shape[0], f.x0)
    x = np.full(f.x0.shape, np.nan)
    for rnd in range(f.rounds):
        rows, clusters, rays = f.batch(f.round_slice(rnd))
        s.accumulate(rows, clusters, rays)
        touched = np.unique(rows)
        x[touched] = s.solve(touched, update_reference=False).x
    return x


def first_rounds(f: Fleet, rounds: int) -> Fleet:
    """The fleet cut after ``rounds`` rounds."""
    stop = int(f.starts[rounds])
    return Fleet(
        f.x_true,
        f.x0,
        f.rows[:stop],
        f.clusters[:stop],
        f.rays.take(np.arange(stop)),
        f.starts[: rounds + 1],
    )


def run_per_ray_loop(f: Fleet, cfg: EstimatorConfig, cls: type = LandmarkSums) -> np.ndarray:
    s = cls(cfg, capacity=f.x0.shape[0])
    s.new_rows(f.x0.shape[0], f.x0)
    x = np.full(f.x0.shape, np.nan)
    o, d = f.rays.origin, f.rays.direction
    sa, se, sh, sv = f.rays.sigma_az, f.rays.sigma_el, f.rays.sigma_pos_h, f.rays.sigma_pos_v
    for rnd in range(f.rounds):
        sl = f.round_slice(rnd)
        for j in range(sl.start, sl.stop):
            k = slice(j, j + 1)
            s.accumulate(f.rows[k], f.clusters[k], Rays(o[k], d[k], sa[k], se[k], sh[k], sv[k]))
        touched = np.unique(f.rows[sl])
        x[touched] = s.solve(touched, update_reference=False).x
    return x


def run_rebuild(f: Fleet, cfg: EstimatorConfig) -> np.ndarray:
    """The paper's way with our estimator: at every round, fresh sums over ALL stored rays
    of the touched landmarks (one vectorised ``accumulate``), then the same ``solve``."""
    n = f.x0.shape[0]
    x = np.full(f.x0.shape, np.nan)
    for rnd in range(f.rounds):
        sl = f.round_slice(rnd)
        touched = np.unique(f.rows[sl])
        sel = np.flatnonzero(np.isin(f.rows[: sl.stop], touched))
        s = LandmarkSums(cfg, capacity=n)
        s.new_rows(n, f.x0)
        s.accumulate(f.rows[sel], f.clusters[sel], f.rays.take(sel))
        x[touched] = s.solve(touched, update_reference=False).x
    return x


def paper_closed_form(
    rows: np.ndarray, origin: np.ndarray, direction: np.ndarray, anchor: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's eq. (4) in batch over the given rays: ``(sum P_j) x = sum P_j a_j`` per
    landmark (``P_j = I - d_j d_j^T``, unweighted), and its ray-level sandwich covariance
    ``A^-1 (sum_j g_j g_j^T) A^-1`` with ``g_j = P_j (x - a_j)`` (a second pass over the
    rays: the batch form can afford what the paper reports). Coordinates relative to each
    landmark's ``anchor``; sums by ``np.bincount``; returns (x, cov) for all ``n``
    landmarks (NaN where a landmark has fewer than 2 rays)."""
    a = origin - anchor[rows]
    d = direction
    p6 = np.column_stack(  # P as (EE, NN, UU, EN, EU, NU)
        [
            1 - d[:, 0] ** 2,
            1 - d[:, 1] ** 2,
            1 - d[:, 2] ** 2,
            -d[:, 0] * d[:, 1],
            -d[:, 0] * d[:, 2],
            -d[:, 1] * d[:, 2],
        ]
    )
    pm = sym_to_mat(p6)
    pa = np.einsum("mij,mj->mi", pm, a)

    def total(v: np.ndarray) -> np.ndarray:
        return np.column_stack([np.bincount(rows, v[:, i], n) for i in range(v.shape[1])])

    amat = sym_to_mat(total(p6))
    seen = np.bincount(rows, minlength=n) >= 2
    amat[~seen] = np.eye(3)
    x = np.linalg.solve(amat, total(pa)[:, :, None])[:, :, 0]
    g = np.einsum("mij,mj->mi", pm, x[rows] - a)
    meat = sym_to_mat(total(g[:, SYM_I] * g[:, SYM_J]))
    k = np.linalg.inv(amat)
    cov = k @ meat @ k
    x[~seen] = np.nan
    return x + anchor, cov


def run_paper_batch(f: Fleet, landmarks: np.ndarray | None = None) -> np.ndarray:
    """At every round, each touched landmark re-solved in closed form over ALL its stored
    rays (:func:`paper_closed_form`, vectorised over landmarks)."""
    n = f.x0.shape[0]
    keep = np.ones(f.rows.size, bool) if landmarks is None else np.isin(f.rows, landmarks)
    x = np.full(f.x0.shape, np.nan)
    for rnd in range(f.rounds):
        sl = f.round_slice(rnd)
        touched = np.unique(f.rows[sl][keep[sl]])
        sel = np.flatnonzero(keep[: sl.stop] & np.isin(f.rows[: sl.stop], touched))
        est, _cov = paper_closed_form(
            f.rows[sel], f.rays.origin[sel], f.rays.direction[sel], f.x0, n
        )
        x[touched] = est[touched]
    return x


def run_paper_lsq(f: Fleet, landmarks: np.ndarray) -> np.ndarray:
    """scipy least_squares per landmark per pass on the textbook residuals of all its rays
    (horizontal and vertical orthogonal distances, unweighted: the paper's eq. (4))."""
    az, el = ray_angles(f.rays.direction)
    h = np.column_stack([np.cos(az), -np.sin(az), np.zeros_like(az)])
    v = np.column_stack([-np.sin(el) * np.sin(az), -np.sin(el) * np.cos(az), np.cos(el)])
    x = np.full(f.x0.shape, np.nan)
    est = f.x0.copy()
    for rnd in range(f.rounds):
        stop = int(f.starts[rnd + 1])
        for lmk in landmarks.tolist():
            idx = np.flatnonzero(f.rows[:stop] == lmk)
            a, hh, vv = f.rays.origin[idx], h[idx], v[idx]
            jac = np.concatenate([hh, vv])

            def resid(p: np.ndarray, a=a, hh=hh, vv=vv) -> np.ndarray:
                d = p - a
                return np.concatenate([(d * hh).sum(1), (d * vv).sum(1)])

            fit = least_squares(
                resid, est[lmk], jac=lambda _p, jac=jac: jac, method="lm", xtol=1e-12
            )
            est[lmk] = x[lmk] = fit.x
    return x


# ---------------------------------------------------------------------------- driver


def bench_case(
    k: int,
    landmarks: int,
    per_pass: int,
    lsq_landmarks: int,
    repeat: int,
    seed: int,
    loop_max_obs: int = 20_000,
    other: type | None = None,
) -> dict:
    passes = max(k // per_pass, 1)
    f = make_fleet(landmarks, passes, per_pass, seed)
    n_obs = f.rows.size
    cfg = EstimatorConfig()
    res: dict = {
        "obs_per_landmark": passes * per_pass,
        "landmarks": landmarks,
        "passes": passes,
        "rays_per_pass": per_pass,
        "batch_rays": landmarks * per_pass,
        "observations": n_obs,
    }
    t_inc, all_inc, x_inc = timed(lambda: run_incremental(f, cfg), repeat)
    # the same kernel with the plug-in meat (EstimatorConfig.integrated_meat off): its cost
    plug = replace(cfg, integrated_meat=False)
    t_pm, all_pm, _ = timed(lambda: run_incremental(f, plug), repeat)
    # the loop's cost per ray does not grow with the rounds: run it on the first rounds
    # only (at most loop_max_obs rays), checked against the kernel on the same rounds
    per_round = landmarks * per_pass
    f_loop = first_rounds(f, max(1, min(passes, loop_max_obs // per_round)))
    n_loop = f_loop.rows.size
    t_loop, all_loop, x_loop = timed(lambda: run_per_ray_loop(f_loop, cfg), repeat)
    x_ref = x_inc if f_loop.rounds == f.rounds else run_incremental(f_loop, cfg)
    diff = float(np.nanmax(np.abs(np.asarray(x_ref) - np.asarray(x_loop))))
    t_rb, all_rb, x_rb = timed(lambda: run_rebuild(f, cfg), max(1, repeat // 2))
    rb_diff = float(np.nanmax(np.abs(np.asarray(x_rb) - np.asarray(x_inc))))
    t_pb, all_pb, x_pb = timed(lambda: run_paper_batch(f), repeat)
    sub = np.arange(min(lsq_landmarks, landmarks))
    n_sub = int(np.isin(f.rows, sub).sum())
    t_lsq, all_lsq, x_lsq = timed(lambda: run_paper_lsq(f, sub), max(1, repeat // 2))
    lsq_diff = float(np.nanmax(np.abs(np.asarray(x_lsq)[sub] - np.asarray(x_pb)[sub])))
    kern = LandmarkSums(EstimatorConfig.paper(), capacity=landmarks)
    kern.new_rows(landmarks, f.x0)
    kern.accumulate(f.rows, f.clusters, f.rays)
    pb_diff = float(np.nanmax(np.abs(kern.solve(np.arange(landmarks)).x - np.asarray(x_pb))))
    err = np.linalg.norm(np.asarray(x_inc)[:, :2] - f.x_true[:, :2], axis=1)
    err_p = np.linalg.norm(np.asarray(x_pb)[:, :2] - f.x_true[:, :2], axis=1)
    res["methods"] = {
        "incremental": {"seconds": t_inc, "runs": all_inc, "obs_per_s": n_obs / t_inc},
        "incremental_plugin_meat": {"seconds": t_pm, "runs": all_pm, "obs_per_s": n_obs / t_pm},
        "per_ray_loop": {
            "seconds": t_loop,
            "runs": all_loop,
            "obs_per_s": n_loop / t_loop,
            "rounds": f_loop.rounds,
            "observations": n_loop,
        },
        "rebuild_ours": {"seconds": t_rb, "runs": all_rb, "obs_per_s": n_obs / t_rb},
        "paper_batch": {"seconds": t_pb, "runs": all_pb, "obs_per_s": n_obs / t_pb},
        "paper_lsq": {
            "seconds": t_lsq,
            "runs": all_lsq,
            "obs_per_s": n_sub / t_lsq,
            "landmarks": int(sub.size),
            "observations": n_sub,
        },
    }
    inc = n_obs / t_inc
    res["ratios"] = {
        "incremental_over_per_ray_loop": inc / (n_loop / t_loop),
        "incremental_over_plugin_meat": inc / (n_obs / t_pm),
        "incremental_over_rebuild_ours": inc / (n_obs / t_rb),
        "incremental_over_paper_batch": inc / (n_obs / t_pb),
        "incremental_over_paper_lsq": inc / (n_sub / t_lsq),
    }
    if other is not None:  # another sums.py, side by side on the same rays
        t_o, all_o, x_o = timed(lambda: run_incremental(f, cfg, other), repeat)
        t_ol, all_ol, _ = timed(lambda: run_per_ray_loop(f_loop, cfg, other), repeat)
        res["methods"]["incremental_compare"] = {
            "seconds": t_o,
            "runs": all_o,
            "obs_per_s": n_obs / t_o,
        }
        res["methods"]["per_ray_loop_compare"] = {
            "seconds": t_ol,
            "runs": all_ol,
            "obs_per_s": n_loop / t_ol,
        }
        res["ratios"]["incremental_over_compare"] = t_o / t_inc
        res["ratios"]["per_ray_loop_over_compare"] = t_ol / t_loop
        res["max_abs_diff_compare_m"] = float(
            np.nanmax(np.abs(np.asarray(x_o) - np.asarray(x_inc)))
        )
    res["checks"] = {
        "max_abs_diff_incremental_vs_loop_m": diff,
        "max_abs_diff_rebuild_vs_incremental_m": rb_diff,
        "max_abs_diff_paper_lsq_vs_batch_m": lsq_diff,
        "max_abs_diff_paper_batch_vs_kernel_paper_config_m": pb_diff,
        "median_horizontal_error_incremental_m": float(np.nanmedian(err)),
        "median_horizontal_error_paper_m": float(np.nanmedian(err_p)),
    }
    if not diff <= 1e-9:
        raise AssertionError(f"per-ray loop differs from the batch kernel by {diff} m")
    if not rb_diff <= 1e-6:
        raise AssertionError(f"re-solving from all rays differs from the kernel by {rb_diff} m")
    if not lsq_diff <= 1e-5:
        raise AssertionError(f"least_squares differs from the closed form by {lsq_diff} m")
    if not pb_diff <= 1e-6:
        raise AssertionError(f"closed form differs from the paper-config kernel by {pb_diff} m")
    return res


def _versus(
    report: dict, title: str, header: str, cols: list[tuple[str, str, str, int]]
) -> list[str]:
    """A side-by-side table: per case, ``this / other (ratio)`` for each column."""
    lines = ["", title, "", f"| obs/landmark | {header} |", "|---:" * (len(cols) + 1) + "|"]
    for c in report["cases"]:
        m, r = c["methods"], c["ratios"]
        cells = [
            f"{m[a]['obs_per_s']:,.0f} / {m[b]['obs_per_s']:,.0f} ({r[k]:.{d}f}x)"
            for a, b, k, d in cols
        ]
        lines.append(f"| {c['obs_per_landmark']:,} | " + " | ".join(cells) + " |")
    return lines


def table(report: dict) -> str:
    lines = [
        machine_line(report["machine"]),
        "observations/s (wall); "
        f"median of {report['repeat']} runs; {report['landmarks']} landmarks, "
        f"{report['rays_per_pass']} rays per pass, one pass of every landmark per batch",
        "",
        "| obs/landmark | observations | incremental | per-ray loop | ours re-solved "
        "| paper closed form | paper least_squares | inc/loop | inc/re-solved "
        "| inc/paper closed form | inc/paper lsq |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for c in report["cases"]:
        m, r = c["methods"], c["ratios"]
        lines.append(
            f"| {c['obs_per_landmark']:,} | {c['observations']:,} "
            f"| {m['incremental']['obs_per_s']:,.0f} | {m['per_ray_loop']['obs_per_s']:,.0f} "
            f"| {m['rebuild_ours']['obs_per_s']:,.0f} "
            f"| {m['paper_batch']['obs_per_s']:,.0f} | {m['paper_lsq']['obs_per_s']:,.0f} "
            f"| {r['incremental_over_per_ray_loop']:.1f}x "
            f"| {r['incremental_over_rebuild_ours']:.1f}x "
            f"| {r['incremental_over_paper_batch']:.1f}x "
            f"| {r['incremental_over_paper_lsq']:.1f}x |"
        )
    lines += _versus(
        report,
        "integrated meat (default) against the plug-in meat, same rays, same run:",
        "incremental obs/s: integrated / plug-in",
        [("incremental", "incremental_plugin_meat", "incremental_over_plugin_meat", 2)],
    )
    if report.get("compare_sums"):
        lines += _versus(
            report,
            f"compared with {report['compare_sums']} (same rays, same run):",
            "incremental obs/s: this / other | per-ray loop: this / other",
            [
                ("incremental", "incremental_compare", "incremental_over_compare", 1),
                ("per_ray_loop", "per_ray_loop_compare", "per_ray_loop_over_compare", 1),
            ],
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, one run (smoke test)")
    ap.add_argument("--obs-per-landmark", type=int, nargs="+", default=[10, 100, 1000])
    ap.add_argument("--landmarks", type=int, help="landmarks (default 200, quick 10)")
    ap.add_argument("--rays-per-pass", type=int, default=5)
    ap.add_argument("--lsq-landmarks", type=int, help="landmarks for paper_lsq (5, quick 2)")
    ap.add_argument(
        "--loop-max-obs", type=int, help="rays for the per-ray loop (20000, quick 2000)"
    )
    ap.add_argument("--repeat", type=int, help="runs per method, median (default 3, quick 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--compare-sums",
        type=Path,
        metavar="FILE",
        help="another sums.py: also time its incremental kernel and loop (before/after)",
    )
    ap.add_argument("--json", type=Path, help="also write the results as JSON to this file")
    args = ap.parse_args(argv)
    landmarks = args.landmarks or (10 if args.quick else 200)
    lsq = args.lsq_landmarks or (2 if args.quick else 5)
    repeat = args.repeat or (1 if args.quick else 3)
    loop_max = args.loop_max_obs or (2_000 if args.quick else 20_000)
    other = load_sums_class(args.compare_sums) if args.compare_sums else None
    report: dict = {
        "benchmark": "solver",
        "machine": machine(),
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "quick": args.quick,
        "repeat": repeat,
        "landmarks": landmarks,
        "rays_per_pass": args.rays_per_pass,
        "compare_sums": str(args.compare_sums) if args.compare_sums else None,
        "cases": [],
    }
    for k in args.obs_per_landmark:
        c = bench_case(k, landmarks, args.rays_per_pass, lsq, repeat, args.seed, loop_max, other)
        report["cases"].append(c)
        m = c["methods"]
        print(
            f"{c['obs_per_landmark']:>5} obs/landmark: incremental "
            f"{m['incremental']['obs_per_s']:,.0f} obs/s, "
            f"loop {m['per_ray_loop']['obs_per_s']:,.0f}, "
            f"ours re-solved {m['rebuild_ours']['obs_per_s']:,.0f}, "
            f"paper batch {m['paper_batch']['obs_per_s']:,.0f}, "
            f"paper lsq {m['paper_lsq']['obs_per_s']:,.0f}",
            flush=True,
        )
    print()
    print(table(report))
    write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
