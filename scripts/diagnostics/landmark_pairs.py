"""Same-class landmark pairs of a finished fleet evaluation: how often they were seen in
the same passes and in the same images (docs/experiments/2026-12-unpaired-landmark-kinds.md).

Usage: python scripts/diagnostics/landmark_pairs.py RUN_DIR SEED [MAX_M]
``RUN_DIR/seed-SEED`` is one seed's output of ``hdmap eval fleet --out RUN_DIR`` (its
``fleet.json`` and ``run/var``). Every link of the matcher's association log is counted
for the landmark that holds it at the end (merges followed). For every pair of
same-class landmarks within ``MAX_M`` (default 16 m, gating positions) that both have 20+
linked passes: distance, passes of each, passes with links to both (``copass``), images
with a link to each (``coimg``), and ``share`` = coimg over the images of the pair's
co-passes on the side with fewer; then the published facings' difference, status and
what the evaluation paired them with (``sign N``, or ``unpaired`` with the sign most of
its rays saw). Two distinct signs in view together are seen in one image most of the
time (share 0.3-0.8); a copy of a sign, never (share ~0).
"""

from __future__ import annotations

import json
import sqlite3
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from schemas.logs import AssocGroup


def successors(groups: list[AssocGroup]) -> dict[int, int]:
    """Retired landmark id -> the id that holds its rays at the end."""
    succ: dict[int, int] = {}
    for g in groups:
        n = g.merged_into.size
        succ.update(zip(g.retired[:n].tolist(), g.merged_into.tolist(), strict=True))
    final: dict[int, int] = {}
    for lid in succ:
        j, hops = lid, 0
        while j in succ and hops < 10_000:
            j, hops = succ[j], hops + 1
        final[lid] = j
    return final


def labels(report: dict) -> dict[int, str]:
    """Per landmark id of a ``fleet.json``: ``sN`` paired with sign N, ``UN`` unpaired
    whose linked rays mostly saw sign N."""
    lab = {s["landmark"]: f"s{s['sign']}" for s in report["signs"] if s["found"]}
    for u in report["unpaired"]:
        lab[u["landmark"]] = f"U{u.get('obs_top_sign')}"
    return lab


def true_signs(run: Path) -> dict[tuple[str, int], int]:
    """Per (vehicle, observation id) of a run directory's uploads (its ``truth.npz``, written
    by the fleet evaluation) the true sign's id (-1: a false positive)."""
    truth = np.load(run / "truth.npz")
    return {
        (str(v), int(o)): int(s)
        for v, o, s in zip(truth["vehicle"], truth["obs_id"], truth["sign_id"], strict=True)
    }


def links_by_landmark(groups: list[AssocGroup]) -> tuple[dict, dict]:
    """Per final landmark id: its (vehicle, pass) keys and (vehicle, pass, image) keys."""
    final = successors(groups)
    passes: dict[int, set] = defaultdict(set)
    images: dict[int, set] = defaultdict(set)
    for g in groups:
        for lid, v, p, im in zip(
            g.links.landmark_id.tolist(),
            g.links.vehicle.tolist(),
            g.links.pass_id.tolist(),
            g.obs.image.tolist(),
            strict=True,
        ):
            lid = final.get(lid, lid)
            key = (g.vehicles[v], p)
            passes[lid].add(key)
            images[lid].add((*key, im))
    return passes, images


def main(root: Path, seed: int, max_m: float) -> None:
    run = root / f"seed-{seed}"
    db = sqlite3.connect(f"file:{run / 'run/var/matcher-all/state.sqlite'}?mode=ro", uri=True)
    groups = [
        AssocGroup.from_bytes(b) for (b,) in db.execute("SELECT body FROM log_out ORDER BY gseq")
    ]
    passes, images = links_by_landmark(groups)
    lms = {}
    for lid, cls, x in db.execute("SELECT id, cls, x FROM landmarks"):
        lms[lid % 2**64] = (cls, np.frombuffer(x, float)[:3])
    pub = sqlite3.connect(f"file:{run / 'run/var/publisher-all/state.sqlite'}?mode=ro", uri=True)
    facing = {
        lid: (fd, st) for lid, fd, st in pub.execute("SELECT id, facing_deg, status FROM current")
    }
    report = json.loads((run / "fleet.json").read_text())
    paired = {s["landmark"]: f"sign {s['sign']}" for s in report["signs"] if s["found"]}
    for u in report["unpaired"]:
        paired[u["landmark"]] = f"unpaired (rays of {u.get('obs_top_sign')})"
    ids = sorted(i for i in lms if len(passes[i]) >= 20)
    for a_i, a in enumerate(ids):
        for b in ids[a_i + 1 :]:
            (ca, xa), (cb, xb) = lms[a], lms[b]
            dist = float(np.linalg.norm(xa - xb))
            if ca != cb or dist > max_m:
                continue
            both = passes[a] & passes[b]
            co = len(images[a] & images[b])
            side = min(
                sum(1 for k in images[a] if k[:2] in both),
                sum(1 for k in images[b] if k[:2] in both),
            )
            (fa, sa), (fb, sb) = facing.get(a, (np.nan, -1)), facing.get(b, (np.nan, -1))
            dfacing = abs((fa - fb + 180.0) % 360.0 - 180.0)
            print(
                f"{dist:5.1f} m  passes {len(passes[a]):4d} / {len(passes[b]):4d}  copass "
                f"{len(both):4d}  coimg {co:5d}  share {co / max(side, 1):.2f}  facing "
                f"{dfacing:3.0f} deg  status {sa}/{sb}  {paired.get(a, '-')} | "
                f"{paired.get(b, '-')}"
            )


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else 16.0)
