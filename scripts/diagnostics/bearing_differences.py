"""Same-class landmark pairs linked in one image: observed against predicted bearing difference
(docs/experiments/2026-12-bearing-differences.md).

Usage: python scripts/diagnostics/bearing_differences.py RUN_DIR SEED
For every image of the association log with links to two same-class landmarks (final ids,
merges followed) the difference of the two detections' azimuths (the pose's heading error
cancels) is compared with the difference of the azimuths from the camera to the two final
landmark positions; ``z`` is that residual over the two rays' azimuth sigmas. Per pair of
landmarks within 16 m with 30+ such images: median |z|, share |z| > 3, share where the
swapped assignment fits better, median |observed difference|. Labels: ``sN`` paired with
sign N, ``UN`` unpaired (N: the sign most of its rays saw).
"""

import json
import sqlite3
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from landmark_pairs import labels, successors

from hdmap.geo.geodesy import EnuFrame
from schemas.logs import AssocGroup

root, seed = Path(sys.argv[1]), int(sys.argv[2])
run = root / f"seed-{seed}"
db = sqlite3.connect(f"file:{run / 'run/var/matcher-all/state.sqlite'}?mode=ro", uri=True)
groups = [AssocGroup.from_bytes(b) for (b,) in db.execute("SELECT body FROM log_out ORDER BY gseq")]
final = successors(groups)
lms = {}
for lid, cls, x in db.execute("SELECT id, cls, x FROM landmarks"):
    lms[lid % 2**64] = (cls, np.frombuffer(x, float)[:3])
ids = np.array(list(lms))
X = np.array([lms[i][1] for i in ids])
report = json.loads((run / "fleet.json").read_text())
label = labels(report)
# collect links
rows = defaultdict(list)  # (veh, pass, image) -> list of (lid, cls, lat, lon, h, dir, saz)
for g in groups:
    L, O = g.links, g.obs
    for k in range(len(L.landmark_id)):
        lid = int(L.landmark_id[k])
        lid = final.get(lid, lid)
        if lid not in lms:
            continue
        key = (g.vehicles[int(L.vehicle[k])], int(L.pass_id[k]), int(O.image[k]))
        rows[key].append(
            (lid, int(O.sign_class[k]), O.lat[k], O.lon[k], O.h[k], O.direction[k], O.sigma_az[k])
        )
first = next(iter(rows.values()))[0]
fr = EnuFrame(first[2], first[3], first[4])
XE = fr.from_ecef(X)
pos = {int(i): XE[n] for n, i in enumerate(ids)}
stats = defaultdict(list)


def w(t):
    return (t + np.pi) % (2 * np.pi) - np.pi


for rs in rows.values():
    if len(rs) < 2:
        continue
    for a in range(len(rs)):
        for b in range(a + 1, len(rs)):
            ra, rb = rs[a], rs[b]
            if ra[1] != rb[1] or ra[0] == rb[0]:
                continue
            o = fr.from_geodetic(ra[2], ra[3], ra[4])
            da, db_ = ra[5], rb[5]
            obs = np.arctan2(da[0], da[1]) - np.arctan2(db_[0], db_[1])
            va, vb = pos[ra[0]] - o, pos[rb[0]] - o
            pred = np.arctan2(va[0], va[1]) - np.arctan2(vb[0], vb[1])
            s = np.hypot(ra[6], rb[6])
            res, swp = w(obs - pred) / s, w(obs + pred) / s
            pair = (ra[0], rb[0]) if ra[0] < rb[0] else (rb[0], ra[0])
            if ra[0] > rb[0]:
                res, swp = -res, -swp
            stats[pair].append((res, swp, np.degrees(w(obs)), np.degrees(w(pred))))
out = []
for pair, v in stats.items():
    if len(v) < 30 or np.linalg.norm(pos[pair[0]] - pos[pair[1]]) > 16:
        continue
    v = np.array(v)
    d = np.linalg.norm(pos[pair[0]] - pos[pair[1]])
    out.append(
        (
            label.get(pair[0], "-"),
            label.get(pair[1], "-"),
            d,
            len(v),
            np.median(np.abs(v[:, 0])),
            np.mean(np.abs(v[:, 0]) > 3),
            np.mean(np.abs(v[:, 1]) < np.abs(v[:, 0])),
            np.median(np.abs(v[:, 2])),
        )
    )
out.sort(key=lambda r: -r[4])
print("labelA labelB dist n med|z| frac|z|>3 frac_swap_better med|obsdiff|deg")
for r in out[:40]:
    print("{:>6} {:>6} {:5.1f} {:5d} {:7.2f} {:5.2f} {:5.2f} {:6.2f}".format(*r))
print(
    "pairs",
    len(out),
    "with U:",
    sum(1 for r in out if r[0].startswith("U") or r[1].startswith("U")),
)
zs = np.array([r[4] for r in out if not (r[0].startswith("U") or r[1].startswith("U"))])
print("good pairs med|z| quantiles", np.quantile(zs, [0.5, 0.9, 0.99, 1.0]).round(2))
