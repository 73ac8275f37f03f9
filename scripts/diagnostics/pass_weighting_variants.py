"""The fleet evaluation's town and passes, each sign's true rays summed per pass, and the
estimate of every sign under several ways of combining the passes: which of them stays
consistent (its error along the line of sight averaging out) as the passes grow.

Usage: python scripts/diagnostics/pass_weighting_variants.py GNSS PASSES [EXTRA_AZ_RAD]
(run from ``scripts/diagnostics/``; ``GNSS`` as in ``true_association_fleet.py``;
``EXTRA_AZ_RAD``, default 0.02, is the unreported azimuth noise the "total" rows add to
the compensation: FLEET's per-pass heading bias). Prints, for the signs with 50+ passes
after 160 passes and after ``PASSES``, per variant: horizontal error (mean, median, p95),
the mean error along the sign's mean viewing direction (positive: beyond the sign), the
share of signs inside their horizontal 95 % region, the share more than 1.96 sigma off on
the major axis, and the mean reported sigma. The covariance here is the plain cluster
sandwich (no small-sample, model or shared floor), so only the rows' differences count.

Variants:

- ``W(A_p)``: the solver's pass weights ``(I + A_p S)^-1 A_p`` (``S`` from
  ``EstimatorConfig.pass_sigma_m``), white compensation (what the pipeline does);
- ``unweighted``: the passes' raw sums, white or total compensation;
- ``T(J_p)``: the pass's estimating function multiplied by ``(I + J_p S)^-1`` with ``J_p``
  the predicted (noise-free) information, total compensation;
- ``heading eliminated``: each pass given its own unknown heading offset (a rotation of all
  its rays about their origins; the horizontal residual gains ``delta_p rho``),
  eliminated per pass by its Schur complement with the noise bias of the product
  compensated, unweighted or with ``W``.
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from true_association_fleet import noise_for  # sibling modules: run from their directory
from true_rays import true_rays

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world
from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.pipeline import model_for
from hdmap.mapping.estimator import EstimatorConfig
from hdmap.mapping.estimator.model import (
    effective_sigmas,
    mat_to_sym,
    pass_weighted,
    predicted_information,
    sym_to_mat,
    weights,
)
from hdmap.mapping.estimator.terms import ray_terms
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model

I3 = np.eye(3)
PASS_SIGMA = EstimatorConfig().pass_sigma_m


def pass_sums(which: str, n_passes: int, extra_az: float) -> dict[str, np.ndarray]:
    """Per (sign, pass) with rays: the sums every variant needs, origins relative to the
    sign's true position (the estimate is then its error), reference 1 m off in E and N."""
    noise = noise_for(which)
    cfg = FleetEvalConfig(Path(tempfile.gettempdir()))
    world = evaluation_world(cfg)
    model = model_for(noise, load_vehicle_model())
    fleet_cfg = FleetConfig(n_vehicles=cfg.vehicles, route_length_m=(600.0, 1200.0))
    fleet = Fleet(world, model, noise, fleet_cfg, 0)
    white = EstimatorConfig()
    total = replace(white, extra_sigma_az=extra_az)
    out: dict[str, list] = {k: [] for k in "sign pass a b at bt j dir s v q cvv cvq".split()}
    with tempfile.TemporaryDirectory() as queue:
        agent = VehicleAgent("veh-0001", model, queue)
        for k, p in enumerate(fleet.passes(n_passes)):
            seen = true_rays(world, agent, p, agent.record(p.pass_id, p.fixes, p.detections))
            if seen is None:
                continue
            rays, r = seen
            o = rays.origin - world.signs.position[r]
            xr = np.tile([1.0, 1.0, 0.0], (r.size, 1))
            per_ray: dict[str, np.ndarray] = {}
            per_ray["a"], per_ray["b"] = ray_terms(rays, o, xr, white)
            per_ray["at"], per_ray["bt"] = ray_terms(rays, o, xr, total)
            per_ray["j"] = predicted_information(rays, o, xr, white)
            per_ray["dir"] = rays.direction
            w_h = weights(rays, o, xr, white)[0]
            s_az = effective_sigmas(rays, white)[0]
            az = np.arctan2(rays.direction[:, 0], rays.direction[:, 1])
            zero = np.zeros_like(az)
            h = np.column_stack([np.cos(az), -np.sin(az), zero])  # horizontal normal
            dh = np.column_stack([np.sin(az), np.cos(az), zero])  # d h / d az = -dh
            rho = np.hypot(*(xr - o)[:, :2].T)
            c2 = (w_h * rho * s_az) ** 2
            per_ray["s"] = w_h * rho**2
            per_ray["v"] = (w_h * rho)[:, None] * h
            per_ray["q"] = w_h * rho * np.einsum("ij,ij->i", h, o)
            per_ray["cvv"] = c2[:, None, None] * dh[:, :, None] * dh[:, None, :]
            per_ray["cvq"] = (c2 * np.einsum("ij,ij->i", dh, o))[:, None] * dh
            for s in np.unique(r):
                m = r == s
                out["sign"].append(s)
                out["pass"].append(k)
                for key, val in per_ray.items():
                    out[key].append(val[m].sum(0))
        agent.close()
    return {k: np.array(v) for k, v in out.items()}


def solve(sign: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray, k: int):
    """``x`` solving ``sum_p T_p (A_p x - b_p) = 0`` per sign and its cluster sandwich."""
    big_b, c = np.zeros((k, 3, 3)), np.zeros((k, 3))
    np.add.at(big_b, sign, t @ a)
    np.add.at(c, sign, (t @ b[..., None])[..., 0])
    g_n = np.bincount(sign, minlength=k)
    ok = g_n >= 50
    x, cov = np.full((k, 3), np.nan), np.full((k, 3, 3), np.nan)
    x[ok] = np.linalg.solve(big_b[ok], c[ok][..., None])[..., 0]
    g = (t @ (a @ np.nan_to_num(x[sign])[..., None] - b[..., None]))[..., 0]
    meat = np.zeros((k, 3, 3))
    np.add.at(meat, sign, g[:, :, None] * g[:, None, :])
    bi = np.linalg.inv(big_b[ok])
    cr1 = (g_n[ok] / (g_n[ok] - 1))[:, None, None]
    cov[ok] = bi @ meat[ok] @ np.swapaxes(bi, -1, -2) * cr1
    return x, cov, ok


def report(name: str, x: np.ndarray, cov: np.ndarray, ok: np.ndarray, view: np.ndarray) -> None:
    e = x[ok][:, :2]
    h = np.linalg.norm(e, axis=1)
    along = np.einsum("ij,ij->i", e, view[ok])
    vh = cov[ok][:, :2, :2]
    m2 = np.einsum("ki,kij,kj->k", e, np.linalg.inv(vh), e)
    lam, vec = np.linalg.eigh(vh)
    e_major = np.einsum("ki,ki->k", e, vec[:, :, -1])
    major_out = np.mean(np.abs(e_major) / np.sqrt(lam[:, -1]) > 1.96)
    sig = np.sqrt(np.trace(vh, axis1=1, axis2=2) / 2).mean()
    print(
        f"  {name:32s} mean {h.mean():6.3f} median {np.median(h):6.3f} p95 "
        f"{np.percentile(h, 95):6.3f} along {along.mean():+7.3f} in95 {np.mean(m2 < 5.991):.3f} "
        f"major>1.96 {major_out:.3f} sigma {sig:.3f}"
    )


def variants(d: dict[str, np.ndarray], max_pass: int) -> None:
    keep = d["pass"] < max_pass
    d = {k: v[keep] for k, v in d.items()}
    sign = d["sign"]
    k = int(sign.max()) + 1
    dirs = np.zeros((k, 3))
    np.add.at(dirs, sign, d["dir"])
    norm = np.linalg.norm(dirs[:, :2], axis=1, keepdims=True)
    view = np.divide(dirs[:, :2], norm, out=np.zeros((k, 2)), where=norm > 0)
    a, at, j = sym_to_mat(d["a"]), sym_to_mat(d["at"]), sym_to_mat(d["j"])
    eye = np.broadcast_to(I3, a.shape)
    s2 = np.diag(np.square(PASS_SIGMA))
    print(f"after {max_pass} passes ({int(np.sum(np.bincount(sign) >= 50))} signs with 50+):")
    aw, bw = pass_weighted(d["a"], d["b"], PASS_SIGMA)
    report("W(A_p), white (the pipeline)", *solve(sign, eye, sym_to_mat(aw), bw, k), view)
    report("unweighted, white", *solve(sign, eye, a, d["b"], k), view)
    report("unweighted, total", *solve(sign, eye, at, d["bt"], k), view)
    report("T(J_p), total", *solve(sign, np.linalg.inv(I3 + j @ s2), at, d["bt"], k), view)
    s = d["s"][:, None]
    a2 = a - (d["v"][:, :, None] * d["v"][:, None, :] - d["cvv"]) / s[..., None]
    b2 = d["b"] - (d["v"] * d["q"][:, None] - d["cvq"]) / s
    report("heading eliminated, unweighted", *solve(sign, eye, a2, b2, k), view)
    aw2, bw2 = pass_weighted(mat_to_sym(a2), b2, PASS_SIGMA)
    report("heading eliminated, W", *solve(sign, eye, sym_to_mat(aw2), bw2, k), view)


def main(which: str, n_passes: int, extra_az: float = 0.02) -> None:
    d = pass_sums(which, n_passes, extra_az)
    print(f"{which}: {len(d['sign'])} (sign, pass) sums, total = white + {extra_az} rad")
    for m in sorted({min(160, n_passes), n_passes}):
        variants(d, m)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else 0.02)
