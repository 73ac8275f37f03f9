"""Scale of one shard: solver state per landmark, update throughput, snapshot latency.

Three measurements, one process, one run:

1. **State bytes per landmark.** :attr:`LandmarkSums.bytes_per_landmark` (closed state in
   memory) and ``open_pass_bytes``; the packed blob the solver persists
   (:meth:`LandmarkSums.pack_rows`) and the SQLite bytes per landmark of the solver's own
   table (:class:`services.solver.state.SolverState`, file size after a WAL checkpoint and
   VACUUM, divided by the landmarks), for a state fed ``--passes`` passes per landmark
   exactly as the solver service feeds it (passes left open, closed by eviction only) and
   for the same state with every pass closed. Goal (issue): at most 200 bytes.
2. **Update throughput at 10k, 100k and 1M landmarks in one shard** (``--landmarks``).
   The shard is first filled (``--warm-passes`` passes of 2 rays per landmark, accumulate
   only: the bulk rate is reported too), then ``--batches`` batches of ``--batch-rays``
   rays (a new pass of 5 rays for random landmarks) go through ``accumulate`` + ``solve``
   of the touched landmarks: observations/s and per-batch latency over the batches after
   5 settling ones (timed apart: the first batches after the fill are the first to close
   passes, so they first write the closed-pass arrays ``S_AA``, ``S_Ab``, ``S_bb``; numpy
   asks for transparent huge pages for large arrays and each first write to a 2 MB page
   has the kernel find and zero one: at 1M landmarks the first batch took 0.8-2.7 s on
   this machine, the fifth ~5 ms; a shard reloaded from SQLite has written them all),
   ``pack_rows`` of the
   touched landmarks (what the solver service persists after each batch; not in the
   observations/s), process RSS per landmark. The default fill, 8 passes, is the solver
   service's steady state: it never closes passes, so every landmark keeps
   ``max_open_passes`` (8) open.
3. **Snapshot latency of a full tile** with 100, 1,000, 10,000 landmarks in it
   (``--tile-landmarks``): ``services.publisher.tilemap.snapshot(conn, tile)`` on the
   publisher's SQLite (read-only connection, as the queryable uses), then encoded; and the
   same through a real Zenoh query (router + publisher process started with
   :class:`hdmap.ops.stack.Stack`, ``--no-zenoh`` skips it).

    .venv/bin/python benchmarks/bench_scale.py [--quick] [--json out/bench/scale.json]
"""

from __future__ import annotations

import argparse
import gc
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_codec import make_landmarks
from bench_solver import (
    load_sums_class,
    machine,
    machine_line,
    make_fleet,
    make_signs,
    pass_rays,
    write_json,
)

from hdmap.geo.tiles import quadkeys_of, tile_center
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums
from hdmap.runtime.store import connect
from schemas import LandmarkUpdates, MapSnapshot, Removals, keys
from services.publisher.tilemap import TileMaps, snapshot
from services.solver.state import SolverLandmark, SolverState

TILE_LAT, TILE_LON = 60.1699, 24.9384  # Helsinki


# ---------------------------------------------------------------------------- 1. bytes


def sqlite_bytes(path: Path, sums: LandmarkSums, n: int) -> dict:
    """Persist ``n`` rows with the solver's own table; file bytes per landmark."""
    conn = connect(path)
    st = SolverState(conn)
    home = quadkeys_of(np.array([TILE_LAT]), np.array([TILE_LON]), 16)[0]
    for i in range(n):
        st.put(SolverLandmark((1 << 40) + i, 4, str(home), i, str(home), 3))
    conn.execute("BEGIN")
    st.save(sums.pack_rows)
    conn.execute("COMMIT")
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    conn.execute("VACUUM")
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    page = conn.execute("PRAGMA page_size").fetchone()[0]
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    blob = conn.execute("SELECT AVG(LENGTH(sums)) FROM landmarks").fetchone()[0]
    conn.close()
    size = path.stat().st_size
    return {
        "file_bytes": size,
        "page_size": page,
        "pages": pages,
        "bytes_per_landmark": size / n,
        "mean_blob_bytes": float(blob),
    }


def bench_bytes(n: int, passes: int, tmp: Path) -> dict:
    f = make_fleet(n, passes, 5, seed=3)
    s = LandmarkSums(EstimatorConfig(), capacity=n)
    s.new_rows(n, f.x0)
    for rnd in range(f.rounds):
        rows, clusters, rays = f.batch(f.round_slice(rnd))
        s.accumulate(rows, clusters, rays)
        s.solve(np.unique(rows), update_reference=False)
    rows = np.arange(n)
    open_per = s.n_open_passes / n
    as_service = sqlite_bytes(tmp / "solver_open.sqlite", s, n)
    packed_open = float(np.mean([len(b) for b in s.pack_rows(rows)]))
    s.close_passes()
    packed_closed = float(np.mean([len(b) for b in s.pack_rows(rows)]))
    closed = sqlite_bytes(tmp / "solver_closed.sqlite", s, n)
    return {
        "landmarks": n,
        "passes_per_landmark": passes,
        "in_memory_bytes_per_landmark": s.bytes_per_landmark,
        "open_pass_bytes": s.open_pass_bytes,
        "open_passes_per_landmark_as_service": open_per,
        "packed_bytes_per_landmark_as_service": packed_open,
        "packed_bytes_per_landmark_closed": packed_closed,
        "sqlite_as_service": as_service,
        "sqlite_closed": closed,
        "goal_bytes": 200,
    }


# ---------------------------------------------------------------------------- 2. throughput


def rss() -> int:
    gc.collect()
    return psutil.Process().memory_info().rss


def bench_throughput(
    n: int,
    warm_passes: int,
    batches: int,
    batch_rays: int,
    seed: int = 5,
    cls: type = LandmarkSums,
    settle: int = 5,
) -> dict:
    rng = np.random.default_rng(seed)
    rss0 = rss()
    x_true, theta, x0 = make_signs(n, rng)
    s = cls(EstimatorConfig(), capacity=n)
    s.new_rows(n, x0)
    next_key = 1
    # fill the shard: every landmark gets warm_passes passes of 2 rays (accumulate only)
    chunk = 100_000
    t_warm, warm_obs = 0.0, 0
    for _p in range(warm_passes):
        for lo in range(0, n, chunk):
            idx = np.arange(lo, min(lo + chunk, n))
            lm, rays = pass_rays(x_true[idx], theta[idx], 2, rng)
            clusters = next_key + (idx[lm] // 10)
            t0 = time.perf_counter()
            s.accumulate(idx[lm], clusters, rays)
            t_warm += time.perf_counter() - t0
            warm_obs += lm.size
        next_key += n // 10 + 1
    rss_full = rss()
    per_batch = max(batch_rays // 5, 1)
    lat, pack = [], []
    t_total = 0.0
    first_ms, settle_ms = 0.0, 0.0
    for b in range(batches + settle):
        idx = np.sort(rng.choice(n, size=min(per_batch, n), replace=False))
        lm, rays = pass_rays(x_true[idx], theta[idx], 5, rng)
        order = rng.permutation(lm.size)
        rows, rays = idx[lm][order], rays.take(order)
        clusters = next_key + lm[order] // 10
        next_key += per_batch // 10 + 1
        t0 = time.perf_counter()
        s.accumulate(rows, clusters, rays)
        s.solve(idx, update_reference=False)
        dt = time.perf_counter() - t0
        s.pack_rows(idx)  # what the solver service then persists (not in obs_per_s)
        if b < settle:  # the first batches after the fill are reported apart (docstring)
            first_ms = first_ms or dt * 1e3
            settle_ms += dt * 1e3
            continue
        pack.append(time.perf_counter() - t0 - dt)
        lat.append(dt)
        t_total += dt
    obs = batches * per_batch * 5
    a = np.array(lat)
    return {
        "landmarks": n,
        "warm_passes": warm_passes,
        "warm_obs": warm_obs,
        "warm_obs_per_s_accumulate_only": warm_obs / t_warm,
        "open_passes": s.n_open_passes,
        "batches": batches,
        "batch_rays": per_batch * 5,
        "observations": obs,
        "obs_per_s": obs / t_total,
        "first_batch_ms": first_ms,
        "settle_batches": settle,
        "settle_ms_total": settle_ms,
        "batch_ms_p50": float(np.percentile(a, 50) * 1e3),
        "batch_ms_p99": float(np.percentile(a, 99) * 1e3),
        "pack_rows_ms_p50": float(np.percentile(pack, 50) * 1e3),
        "obs_per_s_with_pack_rows": obs / (t_total + sum(pack)),
        "rss_bytes_per_landmark": (rss_full - rss0) / n,
    }


# ---------------------------------------------------------------------------- 3. snapshots


def tile_landmarks(n: int, tile: str, seed: int):
    lm = make_landmarks(n, seed)
    lat, lon = tile_center(tile)
    rng = np.random.default_rng(seed)
    lm.lat[:] = lat + rng.uniform(-0.002, 0.002, n)
    lm.lon[:] = lon + rng.uniform(-0.004, 0.004, n)
    lm.id[:] = np.arange(n, dtype=np.uint64) + (seed << 32)
    return lm


def build_publisher_db(path: Path, sizes: list[int]) -> dict[int, str]:
    """A publisher database with one full tile per size; returns size -> tile."""
    base = quadkeys_of(np.array([TILE_LAT]), np.array([TILE_LON]), 16)[0]
    tiles = {}
    conn = connect(path)
    maps = TileMaps(conn)
    for i, n in enumerate(sizes):
        tile = str(base)[:-2] + f"{i // 4 % 4}{i % 4}"  # sibling tiles of one zoom-14 tile
        lm = tile_landmarks(n, tile, seed=i + 1)
        none = Removals(id=np.zeros(0, np.uint64), revision=np.zeros(0, np.uint64))
        conn.execute("BEGIN")
        maps.apply(tile, LandmarkUpdates(lm, none))
        maps.flush()
        conn.execute("COMMIT")
        tiles[n] = tile
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    conn.close()
    return tiles


def stats_ms(times: list[float]) -> dict:
    a = np.array(times) * 1e3
    return {
        "p50_ms": float(np.percentile(a, 50)),
        "p99_ms": float(np.percentile(a, 99)),
        "min_ms": float(a.min()),
        "n": len(times),
    }


def bench_snapshot_direct(db: Path, tiles: dict[int, str], repeat: int) -> list[dict]:
    conn = connect(db, readonly=True)
    out = []
    for n, tile in tiles.items():
        snap = snapshot(conn, tile)
        assert len(snap.landmarks) == n, (len(snap.landmarks), n)
        data = snap.to_bytes()
        t_read, t_enc, t_dec = [], [], []
        for _ in range(repeat):
            t0 = time.perf_counter()
            snap = snapshot(conn, tile)
            t1 = time.perf_counter()
            data = snap.to_bytes()
            t2 = time.perf_counter()
            MapSnapshot.from_bytes(data)
            t3 = time.perf_counter()
            t_read.append(t1 - t0)
            t_enc.append(t2 - t1)
            t_dec.append(t3 - t2)
        out.append(
            {
                "landmarks": n,
                "tile": tile,
                "bytes": len(data),
                "snapshot_call": stats_ms(t_read),
                "encode": stats_ms(t_enc),
                "decode": stats_ms(t_dec),
                "landmarks_per_s_snapshot_call": n / statistics.median(t_read),
            }
        )
    conn.close()
    return out


def bench_snapshot_zenoh(data_dir: Path, tiles: dict[int, str], repeat: int) -> list[dict]:
    from hdmap.ops.stack import Stack
    from hdmap.runtime.bus import open_session

    out = []
    with Stack(data_dir) as st:
        st.start_router()
        st.start_service("publisher")
        st.wait_ready([st.service_key("publisher")], timeout=60.0)
        with open_session(st.bus) as sess:
            for n, tile in tiles.items():
                times = []
                for i in range(repeat + 2):
                    t0 = time.perf_counter()
                    replies = [r for r in sess.get(keys.map_snapshot(tile), timeout=30.0) if r.ok]
                    snap = MapSnapshot.from_bytes(replies[0].ok.payload.to_bytes())
                    dt = time.perf_counter() - t0
                    assert len(snap.landmarks) == n, (len(snap.landmarks), n)
                    if i >= 2:  # the first queries warm the route and the reader thread
                        times.append(dt)
                out.append({"landmarks": n, "tile": tile, "query_and_decode": stats_ms(times)})
    return out


# ---------------------------------------------------------------------------- report


def table(report: dict) -> str:
    b = report["state_bytes"]
    lines = [
        machine_line(report["machine"]),
        "",
        f"state bytes per landmark ({b['landmarks']} landmarks x {b['passes_per_landmark']} "
        f"passes; goal <= {b['goal_bytes']}):",
        f"  in memory, closed state: {b['in_memory_bytes_per_landmark']} "
        f"(+ {b['open_pass_bytes']} per open pass; "
        f"{b['open_passes_per_landmark_as_service']:.1f} open per landmark as the service "
        "leaves them)",
        f"  packed: {b['packed_bytes_per_landmark_as_service']:.0f} as the service leaves it, "
        f"{b['packed_bytes_per_landmark_closed']:.0f} with passes closed",
        f"  SQLite file: {b['sqlite_as_service']['bytes_per_landmark']:.0f} as the service "
        f"leaves it, {b['sqlite_closed']['bytes_per_landmark']:.0f} with passes closed",
        "",
        "| landmarks in shard | open passes | fill obs/s (accumulate) | update obs/s "
        "(accumulate+solve) | batch p50 ms | batch p99 ms | pack_rows p50 ms "
        "| first batch ms | RSS bytes/landmark |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for t in report["throughput"]:
        lines.append(
            f"| {t['landmarks']:,} | {t['open_passes']:,} "
            f"| {t['warm_obs_per_s_accumulate_only']:,.0f} | {t['obs_per_s']:,.0f} "
            f"| {t['batch_ms_p50']:.1f} | {t['batch_ms_p99']:.1f} "
            f"| {t['pack_rows_ms_p50']:.1f} | {t['first_batch_ms']:.1f} "
            f"| {t['rss_bytes_per_landmark']:,.0f} |"
        )
    if report.get("compare_sums"):
        lines += [
            "",
            f"compared with {report['compare_sums']} (same rays, same run):",
            "",
            "| landmarks in shard | update obs/s: this / other | batch p50 ms: this / other "
            "| pack_rows p50 ms: this / other |",
            "|---:|---:|---:|---:|",
        ]
        for t, o in zip(report["throughput"], report["throughput_compare"], strict=True):
            lines.append(
                f"| {t['landmarks']:,} | {t['obs_per_s']:,.0f} / {o['obs_per_s']:,.0f} "
                f"| {t['batch_ms_p50']:.1f} / {o['batch_ms_p50']:.1f} "
                f"| {t['pack_rows_ms_p50']:.1f} / {o['pack_rows_ms_p50']:.1f} |"
            )
    lines += [
        "",
        "| landmarks in tile | snapshot bytes | snapshot() p50 ms | encode p50 ms "
        "| decode p50 ms | Zenoh query+decode p50 ms | p99 ms |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    zen = {z["landmarks"]: z for z in report.get("snapshot_zenoh") or []}
    for d in report["snapshot_direct"]:
        z = zen.get(d["landmarks"])
        zq = f"{z['query_and_decode']['p50_ms']:.2f}" if z else "n/a"
        zp = f"{z['query_and_decode']['p99_ms']:.2f}" if z else "n/a"
        lines.append(
            f"| {d['landmarks']:,} | {d['bytes']:,} | {d['snapshot_call']['p50_ms']:.2f} "
            f"| {d['encode']['p50_ms']:.2f} | {d['decode']['p50_ms']:.2f} | {zq} | {zp} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    ap.add_argument("--landmarks", type=int, nargs="+", help="shard sizes (10k 100k 1M)")
    ap.add_argument("--warm-passes", type=int, default=8, help="(= max_open_passes)")
    ap.add_argument("--batches", type=int, help="measured batches per size (30, quick 5)")
    ap.add_argument("--batch-rays", type=int, default=1000)
    ap.add_argument("--passes", type=int, default=12, help="passes per landmark for bytes")
    ap.add_argument("--bytes-landmarks", type=int, help="landmarks for bytes (5000, quick 500)")
    ap.add_argument("--tile-landmarks", type=int, nargs="+", help="(100 1000 10000)")
    ap.add_argument("--repeat", type=int, help="snapshot queries per size (30, quick 5)")
    ap.add_argument("--no-zenoh", action="store_true", help="skip the Zenoh snapshot query")
    ap.add_argument(
        "--compare-sums",
        type=Path,
        metavar="FILE",
        help="another sums.py: also run the throughput with it, same rays (before/after)",
    )
    ap.add_argument("--json", type=Path, help="also write the results as JSON to this file")
    args = ap.parse_args(argv)
    q = args.quick
    sizes = args.landmarks or ([1_000, 10_000] if q else [10_000, 100_000, 1_000_000])
    batches = args.batches or (5 if q else 30)
    tile_sizes = args.tile_landmarks or ([100, 1_000] if q else [100, 1_000, 10_000])
    repeat = args.repeat or (5 if q else 30)
    report: dict = {
        "benchmark": "scale",
        "machine": machine(),
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "quick": q,
    }
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        n_bytes = args.bytes_landmarks or (500 if q else 5_000)
        report["state_bytes"] = bench_bytes(n_bytes, args.passes, tmp)
        print(f"state bytes: {report['state_bytes']['sqlite_as_service']}", flush=True)
        report["throughput"] = []
        report["compare_sums"] = str(args.compare_sums) if args.compare_sums else None
        report["throughput_compare"] = []
        other = load_sums_class(args.compare_sums) if args.compare_sums else None
        for n in sizes:
            t = bench_throughput(n, args.warm_passes, batches, args.batch_rays)
            report["throughput"].append(t)
            print(
                f"{n:>9,} landmarks: fill {t['warm_obs_per_s_accumulate_only']:,.0f} obs/s, "
                f"update {t['obs_per_s']:,.0f} obs/s, batch p50 {t['batch_ms_p50']:.1f} ms",
                flush=True,
            )
            gc.collect()
            if other is not None:  # the other sums.py, same seed: the same rays
                t_o = bench_throughput(n, args.warm_passes, batches, args.batch_rays, cls=other)
                report["throughput_compare"].append(t_o)
                print(f"{n:>9,} landmarks, {args.compare_sums}: {t_o['obs_per_s']:,.0f} obs/s")
                gc.collect()
        data_dir = tmp / "stack"
        db = data_dir / "publisher-all" / "state.sqlite"
        tiles = build_publisher_db(db, tile_sizes)
        report["snapshot_direct"] = bench_snapshot_direct(db, tiles, repeat)
        print("snapshot (direct) done", flush=True)
        report["snapshot_zenoh"] = None
        if not args.no_zenoh:
            report["snapshot_zenoh"] = bench_snapshot_zenoh(data_dir, tiles, repeat)
            print("snapshot (Zenoh) done", flush=True)
    print()
    print(table(report))
    write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
