"""Whether a landmark's box ranges agree with where its bearings put it: every confirmed
landmark of a finished fleet evaluation, with its rays' mean relative range (the panel
scale, :mod:`hdmap.mapping.box_ranges`) at its published position and at its true sign's.

Usage: python scripts/diagnostics/range_consistency.py RUN_DIR SEED [gnss=gsdc] [MIN_PASSES]
``RUN_DIR/seed-SEED`` is one seed's output of ``hdmap eval fleet --out RUN_DIR`` (its
``run/var`` databases and ``run/truth.npz``). Rays are the matcher's links (merges
followed); a ray's true sign is from the run's truth. Per landmark: passes, rays, the
spread of its rays' bearings, its error along and across the mean line of sight, its
published major sigma, the scale at its position (``s``) and at its sign's (``s_true``),
``z = ln(s) / 0.10`` (the catalogue's panel spread), the fit of ``u = s (1 + delta / r)``
over all its rays at once (``delta``, ``se``) and the looming check's ``delta`` with its
standard deviation (:func:`hdmap.mapping.looming.discrepancy`, passes by their keys, at the
published covariance: where the run's solver widened it, ``|t|`` is 1). Prints the
unpaired confirmed landmarks in full and, for the paired ones, the distribution of ``z``
and ``t`` and how they relate to the error along the line of sight.
"""

from __future__ import annotations

import sqlite3
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np
from landmark_pairs import (
    successors,
    true_signs,
)  # a sibling module: scripts run from their directory

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world
from fleetsim.truth import match_landmarks
from hdmap.geo.geodesy import enu_rotation
from hdmap.mapping import box_ranges, looming
from schemas import STATUS_CONFIRMED
from schemas.logs import AssocGroup

PANEL_REL_SIGMA = 0.10


def main(root: Path, seed: int, gnss: str, min_passes: int) -> None:
    run = root / f"seed-{seed}" / "run"
    world = evaluation_world(FleetEvalConfig(out=Path(tempfile.gettempdir()), seed=seed, gnss=gnss))
    true_sign = true_signs(run)
    db = sqlite3.connect(f"file:{run / 'var/matcher-all/state.sqlite'}?mode=ro", uri=True)
    groups = [
        AssocGroup.from_bytes(b) for (b,) in db.execute("SELECT body FROM log_out ORDER BY gseq")
    ]
    final = successors(groups)
    rays: dict[int, list] = defaultdict(list)
    for gi, g in enumerate(groups):
        ob = g.obs
        origin = world.frame.from_geodetic(ob.lat, ob.lon, ob.h).reshape(-1, 3)
        rot = enu_rotation(ob.lat, ob.lon)  # ENU at A -> ECEF is rot^T
        d_ecef = np.einsum("kji,kj->ki", rot, ob.direction)
        d_world = d_ecef @ world.frame.rotation.T
        for k, lid in enumerate(g.links.landmark_id.tolist()):
            v = g.vehicles[int(g.links.vehicle[k])]
            rays[final.get(lid, lid)].append(
                (
                    origin[k],
                    d_world[k],
                    float(ob.range_m[k]),
                    float(ob.sigma_range_m[k]),
                    float(ob.sigma_pos_h[k]),
                    (int(g.links.pass_id[k]) ^ hash(v)) + (gi * 7919 if BY_GROUP else 0),
                    true_sign.get((v, int(ob.obs_id[k])), -2),
                )
            )
    pub = sqlite3.connect(f"file:{run / 'var/publisher-all/state.sqlite'}?mode=ro", uri=True)
    rows = pub.execute(
        "SELECT id, sign_class, lat, lon, h, cov, status, n_obs, n_passes FROM current"
    ).fetchall()
    ids = np.array([r[0] % 2**64 for r in rows], np.uint64)
    lat, lon, hh = (np.array([r[k] for r in rows], float) for k in (2, 3, 4))
    est = world.frame.from_geodetic(lat, lon, hh).reshape(-1, 3)
    covs = np.stack([_cov(r[5]) for r in rows])
    status = np.array([r[6] for r in rows])
    passes = np.array([r[8] for r in rows])
    cls = np.array([r[1] for r in rows])
    sel = (status == STATUS_CONFIRMED) & (passes >= min_passes)
    signs = world.signs
    sign_row = {int(s): i for i, s in enumerate(signs.id.tolist())}
    m = match_landmarks(world, lat, lon, hh, cls, 5.0, status == STATUS_CONFIRMED)
    paired_ids = {int(ids[j]) for j in m.landmark.tolist()}
    out = []
    for j in np.flatnonzero(sel).tolist():
        lid = int(ids[j])
        rs = rays.get(lid, [])
        if not rs:
            continue
        a = np.array([r[0] for r in rs])
        d = np.array([r[1] for r in rs])
        rng = np.array([r[2] for r in rs])
        srng = np.array([r[3] for r in rs])
        sh = np.array([r[4] for r in rs])
        tsid = np.array([r[6] for r in rs])
        ok = tsid >= 0
        top = int(np.bincount(tsid[ok]).argmax()) if ok.any() else -1
        h, w = box_ranges.ray_terms(a, d, rng, srng, sh, PANEL_REL_SIGMA)
        s = box_ranges.summed(np.zeros(len(rs), np.int64), h, w)
        x = est[j]
        s_hat = float(box_ranges.mean_relative_range(s, x[None])[0])
        xt = signs.position[sign_row[top]] if top in sign_row else np.full(3, np.nan)
        s_true = (
            float(box_ranges.mean_relative_range(s, xt[None])[0]) if top in sign_row else np.nan
        )
        los = (x - a)[:, :2]
        az = np.arctan2(los[:, 0], los[:, 1])
        mean_dir = np.array([np.sin(az).mean(), np.cos(az).mean()])
        r_len = np.linalg.norm(mean_dir)
        spread = np.degrees(np.sqrt(-2 * np.log(max(r_len, 1e-12))))
        u = mean_dir / max(r_len, 1e-12)
        e = (x - xt)[:2]
        along, across = float(e @ u), float(e @ np.array([u[1], -u[0]]))
        dist = float(np.mean(np.linalg.norm(los, axis=1)))
        sig = float(np.sqrt(np.linalg.eigvalsh(covs[j][:2, :2])[-1]))
        z = np.log(s_hat) / PANEL_REL_SIGMA if s_hat > 0 else np.nan
        disp, delta, se = _fit(h, w, x)
        lo_d, lo_se, lo_q, lo_a = _looming(h, w, np.array([r[5] for r in rs]), x, covs[j])
        if lid in SHOW:
            _show(lid, x, a, d, rng, h, w, tsid, signs, sign_row)
        out.append(
            (
                lid in paired_ids,
                lid,
                int(cls[j]),
                int(passes[j]),
                len(rs),
                spread,
                along,
                across,
                dist,
                sig,
                s_hat,
                s_true,
                z,
                top,
                float(ok.mean()) if ok.any() else 0.0,
                float((tsid == top).mean()),
                disp,
                delta,
                se,
                lo_d,
                lo_se,
                lo_q,
                lo_a,
            )
        )
    hdr = (
        "paired id cls passes rays spread_deg along across mean_range sigma s s_true z top "
        "true_share top_share disp delta se loom loom_sd"
    )
    print(hdr)
    for o in out:
        if not o[0]:
            print("FALSE", *[f"{v:.3f}" if isinstance(v, float) else v for v in o[1:]])
    p = np.array([o for o in out if o[0]], dtype=object)
    if len(p):
        z = p[:, 12].astype(float)
        along = p[:, 6].astype(float)
        sig = p[:, 9].astype(float)
        print(
            f"paired confirmed: {len(p)}; z quantiles 1/5/50/95/99 %:",
            np.round(np.nanpercentile(z, [1, 5, 50, 95, 99]), 2).tolist(),
        )
        print(
            "  |z| > 2:",
            int((np.abs(z) > 2).sum()),
            " > 2.5:",
            int((np.abs(z) > 2.5).sum()),
            " > 3:",
            int((np.abs(z) > 3).sum()),
        )
        print(
            "  corr(z, along/range):",
            round(float(np.corrcoef(z, along / p[:, 8].astype(float))[0, 1]), 3),
        )
        disp = p[:, 16].astype(float)
        delta = p[:, 17].astype(float)
        se = p[:, 18].astype(float)
        print(
            "  dispersion quantiles 50/90/99/max:",
            np.round(np.nanpercentile(disp, [50, 90, 99, 100]), 2).tolist(),
        )
        print(
            "  delta quantiles 1/5/50/95/99:",
            np.round(np.nanpercentile(delta, [1, 5, 50, 95, 99]), 2).tolist(),
        )
        print(
            "  delta/se quantiles 1/5/50/95/99:",
            np.round(np.nanpercentile(delta / se, [1, 5, 50, 95, 99]), 2).tolist(),
        )
        po = p[:, 19].astype(float) / p[:, 20].astype(float)
        print(
            "  looming t quantiles 0.5/1/5/50/95/99/99.5:",
            np.round(np.nanpercentile(po, [0.5, 1, 5, 50, 95, 99, 99.5]), 2).tolist(),
            " |t| > 3:",
            int((np.abs(po) > 3).sum()),
            " > 4:",
            int((np.abs(po) > 4).sum()),
        )
        q, a_ = p[:, 21].astype(float), p[:, 22].astype(float)
        ok = a_ > 0
        print(
            "  passes' shared error along the slope (tau, m): pooled",
            round(float(np.sqrt(max(q[ok].sum() / a_[ok].sum(), 0.0))), 2),
            "per landmark 10/50/90/99/100 %:",
            np.round(
                np.sqrt(np.maximum(np.percentile(q[ok] / a_[ok], [10, 50, 90, 99, 100]), 0)), 2
            ).tolist(),
        )
        print("  corr(delta, along):", round(float(np.corrcoef(delta, along)[0, 1]), 3))
        big = np.abs(along) > 3
        print(
            "  paired with |along| > 3 m:",
            int(big.sum()),
            "their z:",
            np.round(z[big], 2).tolist(),
            "sigma:",
            np.round(sig[big], 2).tolist(),
        )


SHOW: set[int] = set()
BY_GROUP = False
"""With ``pieces=group``: a pass's rays in one assoc group are one piece (as the solver sums
them), not the whole pass."""


def _show(lid, x, a, d, rng, h, w, tsid, signs, sign_row) -> None:
    """One landmark's rays by true sign: count, mean range, mean viewing azimuth (from
    the camera, degrees), relative range at the landmark and at that sign."""
    print(f"landmark {lid} at E/N/U {np.round(x, 2).tolist()}")
    for t in np.unique(tsid).tolist():
        k = tsid == t
        az = np.degrees(np.arctan2(d[k, 0], d[k, 1]))
        u_x = h[k, :3] @ x + h[k, 3]
        pos = signs.position[sign_row[t]] if t in sign_row else None
        u_t = h[k, :3] @ pos + h[k, 3] if pos is not None else np.full(k.sum(), np.nan)
        ok = w[k] > 0
        print(
            f"  sign {t}: {int(k.sum())} rays, range {np.median(rng[k]):.1f} "
            f"[{np.percentile(rng[k], 5):.1f}-{np.percentile(rng[k], 95):.1f}], azimuth "
            f"{np.median(az):.1f} [{np.percentile(az, 5):.1f}-{np.percentile(az, 95):.1f}], "
            f"u at x {np.median(u_x[ok]):.3f} +- {np.std(u_x[ok]):.3f}, at sign "
            f"{np.median(u_t[ok]):.3f} +- {np.std(u_t[ok]):.3f}"
            + (f", sign at {np.round(pos, 2).tolist()}" if pos is not None else "")
        )


def _fit(h: np.ndarray, w: np.ndarray, x: np.ndarray) -> tuple[float, float, float]:
    """(dispersion, delta, se): the rays' relative ranges at ``x`` about their weighted
    mean, in units of their claimed white variance; and the fit ``u = s (1 + delta / r)``
    (``delta``: how far beyond ``x`` along the rays the ranges put the panel) with its
    standard error from the residuals."""
    use = w > 0
    h, w = h[use], w[use]
    if w.size < 3:
        return np.nan, np.nan, np.nan
    u = h[:, :3] @ x + h[:, 3]
    inv_r = np.linalg.norm(h[:, :3], axis=1)
    sw = w.sum()
    mu = (w * u).sum() / sw
    disp = float((w * (u - mu) ** 2).sum() / mu**2 / (w.size - 1))
    a = np.stack([np.ones_like(u), inv_r], axis=1)
    ata = a.T @ (w[:, None] * a)
    coef = np.linalg.solve(ata, a.T @ (w * u))
    res = u - a @ coef
    s2 = float((w * res**2).sum() / (w.size - 2))
    cov = s2 * np.linalg.inv(ata)
    s0, b = coef
    return disp, float(b / s0), float(np.sqrt(cov[1, 1]) / abs(s0))


TAU_M = 2.5
"""A pass's shared position error per axis the looming statistic allows for (the solver's
``loom_pass_sigma_m``)."""


def _looming(
    h: np.ndarray, w: np.ndarray, key: np.ndarray, x: np.ndarray, cov: np.ndarray
) -> tuple[float, float, float, float]:
    """(delta, sd, q, a): :func:`hdmap.mapping.looming.discrepancy` over the landmark's
    rays, passes by their keys (``TAU_M``); and :func:`hdmap.mapping.looming.shared_scatter`
    (``E q = tau^2 a``: the passes' own slopes' scatter beyond their white part)."""
    _, piece = np.unique(key, return_inverse=True)
    sums = looming.summed(np.zeros(w.size, np.int64), piece.reshape(-1), h, w)
    t, _, spread = looming.discrepancy(sums, x[None], cov[None], TAU_M)
    q, a = looming.shared_scatter(sums, x[None])
    return float(t[0] * np.sqrt(spread[0])), float(np.sqrt(spread[0])), float(q[0]), float(a[0])


def _cov(blob: bytes) -> np.ndarray:
    v = np.frombuffer(blob, float)
    if v.size == 9:
        return v.reshape(3, 3)
    ee, en, eu, nn, nu, uu = v
    return np.array([[ee, en, eu], [en, nn, nu], [eu, nu, uu]])


if __name__ == "__main__":
    args = [a for a in sys.argv[3:] if not a.startswith(("gnss=", "pieces="))]
    BY_GROUP = "pieces=group" in sys.argv[3:]
    gnss = next((a.split("=", 1)[1] for a in sys.argv[3:] if a.startswith("gnss=")), "fleet")
    SHOW.update(int(a) for a in args[1:])
    main(Path(sys.argv[1]), int(sys.argv[2]), gnss, int(args[0]) if args else 50)
