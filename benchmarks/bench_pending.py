"""One vehicle must not stop a region: the matcher's per-upload cost with a pass whose
pending rays never make a landmark (issue #17, point 1).

In-process matcher (``MatcherService`` on real SQLite, each upload applied as a batch in
its own transaction, as the stage loop does), one tile, one vehicle, one pass, two
hostile patterns:

- ``restart``: the vehicle drives past a sign again and again in one pass, and its image
  indices restart in every upload (images 0, 1, 2): the rays meet, but never in the four
  distinct images a candidate needs; 3 rays an upload;
- ``parked``: a parked car sees the same sign from the same spot with no usable range:
  the rays meet, but without the parallax (or the ranges) a candidate needs; 10 rays an
  upload.

The pass's pool is first filled with ``P`` rays of the pattern (written and reloaded, as
after a restart: every pooled ray has been tried), then ``--uploads`` uploads of the
pattern are applied one by one and timed. Side by side in one run:

- ``before``: the budgets off (``pending_max_per_pass = pending_max_per_vehicle =
  quarantine_after = init_reseed_max = 0``): every upload re-runs initiation over all
  of the pass's pending rays, O(P^2);
- ``seeds``: only ``init_reseed_max`` (64; no caps): above 64 waiting rays, the upload's
  new rays seed: O(upload x P);
- ``after``: the defaults (per-pass cap 256 per tile, new seeds above 64, quarantine
  after 8 failed attempts at the cap).

Reported per (mode, pattern, P): the first upload (with the eviction down to the cap),
the median of the next ones, and the median of the last ones (for ``after``: quarantined
by then), in milliseconds per upload; the pass's pending rays at the end; the counters
(``pending_evicted``, ``passes_quarantined``, ``init_rays`` and ``init_seeds`` per upload).

    .venv/bin/python benchmarks/bench_pending.py [--quick] [--json out/bench/pending.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, machine_line, write_json
from fleetsim.synthetic import ray_observations
from hdmap.geo.tiles import quadkeys_of
from schemas import LogEntry, Observations, ObsGroup
from schemas.ids import pass_key
from services.matcher.replay import open_matcher
from services.matcher.service import MatcherConfig

LAT, LON = 60.17, 24.94
SIGN = np.array([10.0, 30.0, 2.5])
CLS = 7
VEHICLE, PASS = "veh-hostile", 1

MODES = {
    "before": MatcherConfig(
        pending_max_per_pass=0,
        pending_max_per_vehicle=0,
        quarantine_after=0,
        init_reseed_max=0,
    ),
    "seeds": MatcherConfig(pending_max_per_pass=0, pending_max_per_vehicle=0, quarantine_after=0),
    "after": MatcherConfig(),
}
PATTERNS = {"restart": 3, "parked": 10}
"""Pattern: rays per upload."""


def upload_rays(frame, pattern: str, k: int, rng: np.random.Generator) -> Observations:
    """Upload ``k`` of the pass in ``pattern`` (obs ids unique over the pass)."""
    n = PATTERNS[pattern]
    if pattern == "restart":  # three images along 22 m of road, indices 0, 1, 2
        a = np.c_[np.full(n, 12.0), np.linspace(0.0, 22.0, n), np.full(n, 1.5)]
        image = np.arange(n)
    else:  # one spot, GNSS jitter of a standing car, images counting up
        a = np.array([12.0, 0.0, 1.5]) + rng.normal(0, 0.01, (n, 3))
        image = np.arange(n) + k * n
    # a moving pass's GNSS bias drifts between uploads; a standing car's does not
    a_meas = a + (np.r_[rng.normal(0, 0.3, 2), 0.0] if pattern == "restart" else 0.0)
    v = SIGN - a + rng.normal(0, 0.005, (n, 3)) * np.linalg.norm(SIGN - a, axis=1)[:, None]
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    lat, lon, h = frame.to_geodetic(a_meas)
    return ray_observations(lat, lon, h, d, image, np.arange(n) + 100 * k, CLS)


def run_one(mode: str, pattern: str, pool: int, uploads: int, seed: int = 0) -> dict:
    """Fill the pass's pool with ``pool`` rays, then time ``uploads`` uploads."""
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        svc = open_matcher(Path(tmp), MODES[mode])
        opts = svc.opts
        tile = str(quadkeys_of(np.array([LAT]), np.array([LON]), opts.zoom)[0])
        frame = svc.frames(tile)
        per = PATTERNS[pattern]
        k = 0
        parts = []
        while sum(len(p) for p in parts) < pool:
            parts.append(upload_rays(frame, pattern, k, rng))
            k += 1
        filled = Observations.concat(parts)
        filled = filled.take(np.arange(pool))
        now = time.time()
        with svc.transaction([svc]):
            svc.state.add_pending(tile, filled, VEHICLE, PASS, now, now)
            svc.state.save(svc.sums.pack_rows)
        svc._reload()  # as after a restart: every pooled ray was tried as it came
        times = []
        start = dict(svc.counters)
        for seq in range(1, uploads + 1):
            obs = upload_rays(frame, pattern, k, rng)
            k += 1
            g = ObsGroup(VEHICLE, PASS, seq, time.time(), obs)
            e = LogEntry("obs", "bench-ingest", tile, seq, seq, g.to_bytes())
            t0 = time.perf_counter()
            svc._apply_in_transaction([e])
            times.append(time.perf_counter() - t0)
        key = pass_key(VEHICLE, PASS)
        left = int((svc.state.pending[tile].key == key).sum())
        c = {n: svc.counters.get(n, 0) - start.get(n, 0) for n in svc.counters}
        svc.db.close()
    head = max(1, min(3, (uploads - 1) // 2))
    return {
        "mode": mode,
        "pattern": pattern,
        "pool": pool,
        "upload_rays": per,
        "uploads": uploads,
        "first_ms": times[0] * 1e3,
        "next_ms": statistics.median(times[1 : 1 + head]) * 1e3 if uploads > 1 else None,
        "last_ms": statistics.median(times[-head:]) * 1e3,
        "max_ms": max(times) * 1e3,
        "pending_after": left,
        "created": int(c.get("created", 0)),
        "pending_evicted": int(c.get("pending_evicted", 0)),
        "passes_quarantined": int(c.get("passes_quarantined", 0)),
        "init_rays_per_upload": c.get("init_rays", 0) / uploads,
        "init_seeds_per_upload": c.get("init_seeds", 0) / uploads,
        "times_ms": [t * 1e3 for t in times],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pools", type=int, nargs="+", default=[4, 400, 1400])
    p.add_argument("--uploads", type=int, default=12, help="uploads timed per case (after)")
    p.add_argument(
        "--before-uploads", type=int, default=3, help="uploads timed per case (before, seeds)"
    )
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--quick", action="store_true", help="smaller pools, fewer uploads")
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    pools = [4, 200] if a.quick else a.pools
    m = machine()
    print(machine_line(m), flush=True)
    print(
        f"{'mode':>7} {'pattern':>8} {'P':>5} {'rays':>4} {'first':>9} {'next':>9} "
        f"{'last':>9} {'P after':>7} {'evicted':>7} {'quar.':>5} {'rays/up':>7} {'seeds/up':>8}"
    )
    rows = []
    run_one("after", "restart", 4, 2)  # warm up (imports, caches)
    for pattern in PATTERNS:
        for pool in pools:
            for mode in a.modes:
                n = a.uploads if mode == "after" else a.before_uploads
                n = min(n, 10) if a.quick else n
                r = run_one(mode, pattern, pool, n)
                rows.append(r)
                nxt = "-" if r["next_ms"] is None else f"{r['next_ms']:7.1f}ms"
                print(
                    f"{mode:>7} {pattern:>8} {pool:5d} {r['upload_rays']:4d} "
                    f"{r['first_ms']:7.1f}ms {nxt:>9} {r['last_ms']:7.1f}ms "
                    f"{r['pending_after']:7d} {r['pending_evicted']:7d} "
                    f"{r['passes_quarantined']:5d} {r['init_rays_per_upload']:7.0f} "
                    f"{r['init_seeds_per_upload']:8.1f}",
                    flush=True,
                )
    cfg = {k: {f: getattr(c, f) for f in _KNOBS} for k, c in MODES.items()}
    write_json(a.json, {"machine": m, "modes": cfg, "rows": rows})
    return 0


_KNOBS = (
    "pending_max_per_pass",
    "pending_max_per_vehicle",
    "init_reseed_max",
    "quarantine_after",
)


if __name__ == "__main__":
    raise SystemExit(main())
