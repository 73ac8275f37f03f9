"""Region sharding: two matcher+solver pairs on disjoint regions vs one pair for both.

The load generator's town is split into two regions (quadkey prefixes) that each get
about half of its observations (routed to tiles exactly as ingest does). Then, on a
fresh stack each time (router, one ingest, one publisher):

- ``one pair``: one matcher and one solver owning both regions;
- ``two pairs``: a matcher and a solver per region (``hdmap service ... --region``).

Both get the same load, above what one pair sustains (an overload: ``--rate`` for
``--seconds``); the throughput is the observations the matchers processed divided by
load + drain time (``sustained_per_s`` of ``hdmap loadtest``), with zero loss required.
The configurations alternate ``--repeats`` times; the result is the ratio of their median
throughputs (the machine may be shared: the load average is recorded with each run).

The overload is kept moderate on purpose (default 6000 obs/s for 15 s, about twice
what one matcher sustains here): a stage service whose inbox fills up (4096 items,
some 120,000 observations behind) blocks for good, because its worker puts a
catch-up "kick" into its own full inbox (``StageService._mark_catchup``); a heavier
overload measures that hang, not the throughput.

    .venv/bin/python benchmarks/bench_sharding.py [--quick] [--json FILE]
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import bench_zenoh
from benchmarks.bench_e2e import load_average, load_config, step
from fleetsim.loadgen import LoadConfig, build_pool
from hdmap.geo.tiles import DEFAULT_TARGET_RANGE_M, DEFAULT_ZOOM, route_rays
from hdmap.ops.stack import Stack
from hdmap.runtime.bus import open_session
from schemas import Observations


def observation_tiles(cfg: LoadConfig, zoom: int = DEFAULT_ZOOM) -> np.ndarray:
    """The tile of every pool observation, routed like ingest routes it."""
    _world, pool = build_pool(cfg)
    obs = Observations.concat([p for parts in pool for p in parts])
    return route_rays(
        obs.lat, obs.lon, obs.h, obs.direction, obs.range_m, zoom, DEFAULT_TARGET_RANGE_M
    )


def split_regions(tiles: np.ndarray, depth: int = 2) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Two disjoint sets of quadkey prefixes covering every tile, as even as possible.

    Prefixes are the tiles' common prefix extended by ``depth`` digits; the split is the
    subset of them whose observation count is closest to half (exhaustive search)."""
    names = sorted(set(tiles.tolist()))
    first, last = names[0], names[-1]  # sorted: their common prefix is everyone's
    pairs = zip(first, last, strict=False)
    k = next((i for i, (x, y) in enumerate(pairs) if x != y), len(first)) + depth
    prefixes, counts = np.unique(np.array([t[:k] for t in tiles.tolist()]), return_counts=True)
    total = int(counts.sum())
    best: tuple[int, tuple[int, ...]] = (total, ())
    idx = range(len(prefixes))
    for r in range(1, len(prefixes)):
        for subset in itertools.combinations(idx, r):
            gap = abs(total - 2 * int(counts[list(subset)].sum()))
            if gap < best[0]:
                best = (gap, subset)
    chosen = set(best[1])
    a = tuple(str(prefixes[i]) for i in idx if i in chosen)
    b = tuple(str(prefixes[i]) for i in idx if i not in chosen)
    return a, b


def start(st: Stack, pairs: list[tuple[str, ...]]) -> None:
    """Router, ingest, publisher (all tiles) and a matcher+solver pair per region set."""
    st.start_router()
    names = [st.service_key("ingest"), st.service_key("publisher")]
    st.start_service("ingest")
    st.start_service("publisher")
    for k, region in enumerate(pairs):
        # An explicit instance id: the default one embeds the region label, which for
        # several prefixes contains '+', not allowed in ids (such a service's Stats do
        # not decode, so status, quiesce and loadtest would not see it).
        st.start_service("matcher", region, "--instance", f"matcher-pair{k}")
        st.start_service("solver", region, "--instance", f"solver-pair{k}")
        names += [st.service_key("matcher", region), st.service_key("solver", region)]
    st.wait_ready(names, timeout=120.0)


def run_config(
    name: str,
    pairs: list[tuple[str, ...]],
    cfg: LoadConfig,
    workdir: Path,
    drain_timeout: float,
    progress: bool,
) -> dict:
    with Stack(workdir) as st:
        start(st, pairs)
        with open_session(st.bus) as s:
            r = step(s, st, cfg, drain_timeout, progress)
    inst = {
        i: {"region": v["region"], "cpu_share": round(v["cpu_share"], 3)}
        for i, v in r["instances"].items()
        if v["service"] in ("matcher", "solver")
    }
    out = {
        "config": name,
        "pairs": [list(p) for p in pairs],
        "sustained_per_s": r["sustained_per_s"],
        "accepted_per_s": r["accepted_per_s"],
        "load_s": r["load_s"],
        "drain_s": r["drain_s"],
        "zero_loss": r["zero_loss"],
        "failed": r["failed"],
        "retries": r["retries"],
        "losses": r["losses"],
        "observations": r["chain"]["matcher_received"],
        "latency_s": r["latency_s"],
        "services": r["services"],
        "matcher_solver_instances": inst,
        "loadgen": r["loadgen"],
        "router": r["router"],
        "load_average_before": r["load_average_before"],
        "load_average_after": r["load_average_after"],
    }
    cpu = ", ".join(f"{k} {100 * v['cpu_share']:.0f}%" for k, v in sorted(inst.items()))
    print(
        f"{name:<10} sustained {r['sustained_per_s']:7.0f} obs/s ({out['observations']:.0f} obs "
        f"in {r['load_s']:.1f} s load + {r['drain_s']:.1f} s drain), "
        f"{'zero loss' if r['zero_loss'] else 'LOSS'}, failed {r['failed']}; cpu {cpu}; "
        f"load average {r['load_average_after']}",
        flush=True,
    )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one short run per configuration")
    ap.add_argument("--rate", type=float, default=6000.0, help="offered obs/s")
    ap.add_argument("--seconds", type=float, help="load per run (default 15; quick 8)")
    ap.add_argument("--repeats", type=int, help="runs per configuration (default 3; quick 1)")
    ap.add_argument("--drain-timeout", type=float, default=300.0)
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rate = args.rate
    seconds = args.seconds or (8.0 if args.quick else 15.0)
    repeats = args.repeats or (1 if args.quick else 3)
    # An overload: uploads may wait long for their ack; give them time rather than fail.
    cfg = load_config(rate, seconds, upload_timeout_s=30.0)
    tiles = observation_tiles(cfg)
    a, b = split_regions(tiles)
    share_a = float(np.mean([any(t.startswith(p) for p in a) for t in tiles.tolist()]))
    out: dict = {
        "machine": bench_zenoh.machine(),
        "load_average_start": load_average(),
        "offered_per_s": rate,
        "seconds": seconds,
        "vehicles": cfg.vehicles,
        "regions": {"a": list(a), "b": list(b), "share_of_observations_a": share_a},
        "runs": [],
    }
    print(
        json.dumps(out["machine"]),
        f"load average {out['load_average_start']}; regions A {a} ({100 * share_a:.0f}% of obs)"
        f" and B {b}; offered {rate:.0f} obs/s for {seconds:.0f} s",
        flush=True,
    )
    configs = [("one pair", [a + b]), ("two pairs", [a, b])]
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            for name, pairs in configs:
                work = Path(tmp) / f"{name.replace(' ', '-')}-{k}"
                out["runs"].append(
                    run_config(name, pairs, cfg, work, args.drain_timeout, args.progress)
                )
    result = {}
    for name, _pairs in configs:
        runs = [r for r in out["runs"] if r["config"] == name]
        result[name] = {
            "sustained_per_s": statistics.median(r["sustained_per_s"] for r in runs),
            "runs": [round(r["sustained_per_s"]) for r in runs],
            "all_zero_loss": all(r["zero_loss"] for r in runs),
        }
    ratio = result["two pairs"]["sustained_per_s"] / max(result["one pair"]["sustained_per_s"], 1)
    out["result"] = result | {"throughput_ratio": ratio}
    out["load_average_end"] = load_average()
    print(
        f"\none pair {result['one pair']['sustained_per_s']:.0f} obs/s "
        f"{result['one pair']['runs']}, two pairs {result['two pairs']['sustained_per_s']:.0f}"
        f" obs/s {result['two pairs']['runs']}: ratio {ratio:.2f}; zero loss "
        f"{result['one pair']['all_zero_loss'] and result['two pairs']['all_zero_loss']}",
        flush=True,
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
