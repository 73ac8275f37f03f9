"""The fleet evaluation's town and passes, each sign's true rays straight into ``LandmarkSums``:
the estimator's own error, without the matcher.

Usage: python scripts/diagnostics/true_association_fleet.py GNSS PASSES [KNOB=V,...]
``GNSS``: ``fleet`` (FLEET's receiver), ``exact`` (no GNSS error, FLEET's white sigmas
reported), ``exact0`` (no GNSS error, the heading sigma reported as 0.001 deg),
``totals`` (FLEET's errors, the receiver claiming its totals: ``totals_reported``),
``heading_total`` (only the heading's total), ``position_total`` (only the positions'),
``gsdc`` (the replayed phone errors, the course sigma by speed), ``gsdc_const`` (the
same, one course sigma for all speeds), ``white:DEG`` or ``bias:DEG`` (exact positions;
heading errors of DEG, white per fix or one per pass, reported as DEG; ``bias:DEG@C``
reports C).
Prints, over the signs with 50+ passes, the horizontal error, the error along each sign's
weakest direction against its sigma there (:func:`weak_axis`) and, for those more than 1 m
off, how much of it lies along their mean viewing direction (negative: short of the sign).
``KNOB=V,...``: ``EstimatorConfig`` fields to change (numbers; ``compensate=0``), and
``pitch=RAD`` (the vehicle model's claimed pitch noise), ``rate=HZ`` (the GNSS rate),
``yaw=RAD_S2`` (the pose model's yaw acceleration floor), ``box=PX`` (noise on the
boxes' width and height), ``scale=0|1|2`` (box ranges off, ``range_scale`` ``per_pass``,
``inverse``: the ranges enter the sums), ``pass_sigma=M`` (``pass_sigma_m`` = (M, M, M);
0: no pass weights), ``ref=M`` (the weights' reference position M metres East and North
of the sign, default 1).
"""

from __future__ import annotations

import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from true_rays import true_rays  # a sibling module: scripts run from their directory

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world, totals_reported
from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.gnss_replay import gsdc
from fleetsim.noise import FLEET, NoiseModel
from fleetsim.pipeline import model_for
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model
from vehicle.pose import PoseTiming


def noise_for(which: str) -> NoiseModel:
    g = FLEET.gnss
    if which == "fleet":
        return FLEET
    if which in ("totals", "heading_total", "position_total"):
        t = totals_reported(g)
        if which == "heading_total":
            t = replace(g, reported_sigma_heading_deg=t.reported_sigma_heading_deg)
        if which == "position_total":
            t = replace(t, reported_sigma_heading_deg=g.reported_sigma_heading_deg)
        return replace(FLEET, gnss=t)
    if which.startswith(("white:", "bias:")):  # exact positions, one kind of heading error
        kind, spec = which.split(":")
        deg, _, claim = spec.partition("@")
        rad = math.radians(float(deg))
        exact = noise_for("exact").gnss
        return replace(
            FLEET,
            gnss=replace(
                exact,
                white_heading_rad=rad if kind == "white" else 0.0,
                bias_heading_rad=rad if kind == "bias" else 0.0,
                reported_sigma_heading_deg=float(claim or deg),
            ),
        )
    if which in ("gsdc", "gsdc_const"):
        r = gsdc() if which == "gsdc" else replace(gsdc(), velocity_sigma_mps=0.0)
        return replace(FLEET, name="fleet+gsdc", gnss=r)
    heading = 1e-3 if which == "exact0" else math.degrees(g.white_heading_rad)
    exact = replace(
        g,
        white_h_m=0.0,
        white_v_m=0.0,
        white_heading_rad=0.0,
        bias_h_m=0.0,
        bias_v_m=0.0,
        bias_heading_rad=0.0,
        walk_h_m_per_sqrt_s=0.0,
        walk_v_m_per_sqrt_s=0.0,
        multipath_prob=0.0,
        reported_sigma_h_m=g.white_h_m,
        reported_sigma_v_m=g.white_v_m,
        reported_sigma_heading_deg=heading,
    )
    return replace(FLEET, gnss=exact)


def weak_axis(sol, e: np.ndarray, m: np.ndarray, passes: np.ndarray, r_mean: np.ndarray) -> None:
    """The error along each sign's weakest horizontal direction (the major axis of its
    covariance) against its sigma there, by ``G sigma^2 / R`` (the per-pass variance along
    that axis over the mean range: how far the passes' shared errors move a pass's solution
    there, relative to the distance)."""
    i = np.flatnonzero(m & np.isfinite(sol.x[:, 0]))
    if not i.size:
        return
    w, v = np.linalg.eigh(sol.cov[i][:, :2, :2])  # ascending: the major axis is the last
    s_major = np.sqrt(w[:, -1])
    e_w = np.einsum("ki,ki->k", e[i, :2], v[:, :, -1])
    b = passes[i] * w[:, -1] / r_mean[i]
    z = np.abs(e_w) / s_major
    out = np.mean(z > 1.96)
    print(f"major axis: |error| / sigma median {np.median(z):.2f}, outside 1.96 sigma {out:.3f}")
    for lo, hi in ((0, 0.5), (0.5, 2), (2, 8), (8, np.inf)):
        k = (b >= lo) & (b < hi)
        if k.any():
            print(
                f"  G sigma^2 / R in [{lo}, {hi}): {int(k.sum())} signs, |error| median "
                f"{np.median(np.abs(e_w[k])):.2f} m, sigma median {np.median(s_major[k]):.2f}, "
                f"outside 1.96 sigma {np.mean(z[k] > 1.96):.2f}"
            )


def main(which: str, n_passes: int, overrides: str = "") -> None:
    pairs = [kv.split("=") for kv in overrides.split(",") if kv]
    knobs_out = {k: v for k, v in pairs if k == "dump"}  # dump=PATH.npz
    knobs = {k: float(v) for k, v in pairs if k != "dump"}
    noise = noise_for(which)
    if "box" in knobs:
        noise = replace(noise, detector=replace(noise.detector, size_sigma_px=knobs.pop("box")))
    scale = int(knobs.pop("scale", 0))
    ref_off = knobs.pop("ref", 1.0)  # the reference's offset from the sign, m (E and N)
    cfg = FleetEvalConfig(Path(tempfile.gettempdir()))
    world = evaluation_world(cfg)
    model = model_for(noise, load_vehicle_model())
    if "pitch" in knobs:  # the vehicle model's claimed pitch noise, rad
        model = replace(model, pitch_sigma_rad=knobs.pop("pitch"))
    rate = {"gnss_rate_hz": knobs.pop("rate")} if "rate" in knobs else {}
    fleet_cfg = FleetConfig(n_vehicles=cfg.vehicles, route_length_m=(600.0, 1200.0), **rate)
    fleet = Fleet(world, model, noise, fleet_cfg, 0)
    k_signs = len(world.signs)
    passes, dirs = np.zeros(k_signs, int), np.zeros((k_signs, 3))
    ranges, n_rays = np.zeros(k_signs), np.zeros(k_signs)
    with tempfile.TemporaryDirectory() as queue:
        timing = PoseTiming()
        if "yaw" in knobs:  # the pose model's yaw acceleration floor, rad/s^2
            timing = replace(timing, yaw_accel_sigma_radps2=knobs.pop("yaw"))
        agent = VehicleAgent("veh-0001", model, queue, timing=timing)
        ps = knobs.pop("pass_sigma", None)  # one figure for E, N and U, m; 0: no pass weights
        est = EstimatorConfig(
            **{k: type(getattr(EstimatorConfig(), k))(float(v)) for k, v in knobs.items()}
        )
        if ps is not None:
            est = replace(est, pass_sigma_m=(ps, ps, ps))
        if scale:
            est = replace(est, box_range=True, range_scale=("per_pass", "inverse")[scale - 1])
        sums = LandmarkSums(est)
        rows = sums.new_rows(k_signs, world.signs.position + np.array([ref_off, ref_off, 0.0]))
        for k, p in enumerate(fleet.passes(n_passes)):
            seen = true_rays(world, agent, p, agent.record(p.pass_id, p.fixes, p.detections))
            if seen is None:
                continue
            rays, r = seen
            passes[np.unique(r)] += 1
            np.add.at(dirs, r, rays.direction)
            np.add.at(ranges, r, np.linalg.norm(world.signs.position[r] - rays.origin, axis=1))
            np.add.at(n_rays, r, 1)
            sums.accumulate(rows[r], np.full(r.size, k), rays)
        agent.close()
    sol = sums.solve(rows)
    e = sol.x - world.signs.position
    h = np.linalg.norm(e[:, :2], axis=1)
    m = passes >= 50
    print(
        f"{which}, {n_passes} passes: {int(m.sum())} signs with 50+ passes, horizontal error "
        f"mean {np.nanmean(h[m]):.3f} m, median {np.nanmedian(h[m]):.3f}, p95 "
        f"{np.nanpercentile(h[m], 95):.3f}; mean error vector {np.nanmean(e[m], 0).round(3)}"
    )
    view = dirs[m, :2] / np.linalg.norm(dirs[m, :2], axis=1, keepdims=True)
    along_all = np.einsum("ij,ij->i", e[m, :2], view)
    print(
        f"along the viewing direction (negative: short of the sign): mean "
        f"{np.nanmean(along_all):.3f} m, median {np.nanmedian(along_all):.3f}"
    )
    weak_axis(sol, e, m, passes, ranges / np.maximum(n_rays, 1))
    if "dump" in knobs_out:  # per sign: error (E, N, U), passes, covariance
        np.savez(knobs_out["dump"], e=e, passes=passes, cov=sol.cov, ids=world.signs.id)
    big = m & (h > 1.0)
    if big.any():
        d = dirs[big, :2] / np.linalg.norm(dirs[big, :2], axis=1, keepdims=True)
        along = np.einsum("ij,ij->i", e[big, :2], d)
        print(
            f"{int(big.sum())} more than 1 m off; along their viewing direction "
            f"{np.round(along, 2).tolist()} m (median share of the error "
            f"{np.median(np.abs(along) / h[big]):.2f})"
        )


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3] if len(sys.argv) > 3 else "")
