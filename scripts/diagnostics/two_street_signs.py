"""Signs seen from two streets: where each street's true rays put the sign.

Usage: python scripts/diagnostics/two_street_signs.py GNSS PASSES SEED SIGN_ID[,SIGN_ID...]
[KNOB=V,...] (from ``scripts/diagnostics/``; ``GNSS`` and the ``EstimatorConfig`` knobs as in
``true_association_fleet.py``). For each sign:
its true rays over the fleet evaluation's passes, split by viewing azimuth into those
within 30 degrees of the sign's facing and the rest; each part solved on its own in
``LandmarkSums``; printed: rays, passes, viewing azimuth and range quartiles, the
solution's error along / across the sign's facing normal (positive: in front of it).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
from true_association_fleet import noise_for
from true_rays import true_rays

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world
from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.pipeline import model_for
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model


def plain_lsq(o, d, s_az, s_pos, box_r=None, box_s=None) -> np.ndarray:
    """Textbook weighted least squares of the rays (perpendicular distances), with box ranges
    as ``d . x = d . a + r`` terms if given (weight 1 / (sigma_r^2 + s_pos^2))."""
    a_mat, b_vec = np.zeros((3, 3)), np.zeros(3)
    for j in range(o.shape[0]):
        p = np.eye(3) - np.outer(d[j], d[j])
        w = 1.0 / (s_pos[j] ** 2 + (40.0 * s_az[j]) ** 2)
        a_mat += w * p
        b_vec += w * p @ o[j]
        if box_r is not None and box_r[j] > 0:
            wr = 1.0 / (box_s[j] ** 2 + s_pos[j] ** 2)
            a_mat += wr * np.outer(d[j], d[j])
            b_vec += wr * d[j] * (d[j] @ o[j] + box_r[j])
    return np.linalg.solve(a_mat, b_vec)


def main(which: str, n_passes: int, seed: int, ids: list[int], overrides: str = "") -> None:
    knobs = {k: float(v) for k, v in (kv.split("=") for kv in overrides.split(",") if kv)}
    est = EstimatorConfig(
        **{k: type(getattr(EstimatorConfig(), k))(float(v)) for k, v in knobs.items()}
    )
    noise = noise_for(which)
    cfg = FleetEvalConfig(Path(tempfile.gettempdir()), seed=seed)
    world = evaluation_world(cfg)
    model = model_for(noise, load_vehicle_model())
    fleet = Fleet(
        world,
        model,
        noise,
        FleetConfig(n_vehicles=cfg.vehicles, route_length_m=(600.0, 1200.0)),
        seed,
    )
    rows = world.signs.index_of(np.array(ids))
    got: dict[int, list] = {int(r): [] for r in rows}
    with tempfile.TemporaryDirectory() as queue:
        agent = VehicleAgent("veh-0001", model, queue)
        for k, p in enumerate(fleet.passes(n_passes)):
            obs = agent.record(p.pass_id, p.fixes, p.detections)
            seen = true_rays(world, agent, p, obs)
            if seen is None:
                continue
            rays, r = seen
            ok = np.flatnonzero(world.signs.index_of(p.truth.sign_id[agent.last_kept]) >= 0)
            sid = p.truth.sign_id[agent.last_kept]
            ok = (sid >= 0) & (world.signs.index_of(sid) >= 0)
            rng_all = np.asarray(obs.range_m)[ok]
            srng_all = np.asarray(obs.sigma_range_m)[ok]
            for row in got:
                m = r == row
                if m.any():
                    got[row].append((k, rays, np.flatnonzero(m), rng_all, srng_all))
        agent.close()
    for row, parts in got.items():
        sign = world.signs.position[row]
        face = np.radians(world.signs.facing_azimuth_deg[row])
        normal = np.array([np.sin(face), np.cos(face)])
        o = np.concatenate([p[1].origin[p[2]] for p in parts]) if parts else np.zeros((0, 3))
        d = np.concatenate([p[1].direction[p[2]] for p in parts]) if parts else np.zeros((0, 3))
        pas = np.concatenate([np.full(p[2].size, p[0]) for p in parts]) if parts else np.zeros(0)
        keep = {
            f: np.concatenate([getattr(p[1], f)[p[2]] for p in parts])
            for f in ("sigma_az", "sigma_el", "sigma_pos_h", "sigma_pos_v")
        }
        box_r = np.concatenate([p[3][p[2]] for p in parts]) if parts else np.zeros(0)
        box_s = np.concatenate([p[4][p[2]] for p in parts]) if parts else np.zeros(0)
        view = np.degrees(np.arctan2(-d[:, 0], -d[:, 1]))
        off = (view - np.degrees(face) + 180.0) % 360.0 - 180.0
        rng = np.linalg.norm(sign[:2] - o[:, :2], axis=1)
        print(
            f"sign {ids[list(got).index(row)]} (class {world.signs.sign_class[row]}, facing {np.degrees(face) % 360:.0f} deg): {o.shape[0]} rays, {np.unique(pas).size} passes"
        )
        for name, m in (("near facing", np.abs(off) <= 30.0), ("oblique", np.abs(off) > 30.0)):
            if m.sum() < 5:
                print(f"  {name}: {int(m.sum())} rays")
                continue
            sums = LandmarkSums(est)
            lm = sums.new_rows(1, sign[None] + np.array([1.0, 1.0, 0.0]))
            rays = Rays(
                o[m],
                d[m],
                keep["sigma_az"][m],
                keep["sigma_el"][m],
                keep["sigma_pos_h"][m],
                keep["sigma_pos_v"][m],
                None,
            )
            sums.accumulate(np.repeat(lm, int(m.sum())), pas[m].astype(np.int64), rays)
            e = sums.solve(lm).x[0] - sign
            q = lambda a: np.percentile(a, [25, 50, 75]).round(1).tolist()  # noqa: E731
            plain = {}
            for with_range in (False, True):
                x_hat = plain_lsq(
                    o[m],
                    d[m],
                    keep["sigma_az"][m],
                    keep["sigma_pos_h"][m],
                    box_r[m] if with_range else None,
                    box_s[m],
                )
                plain[with_range] = np.hypot(*(x_hat - sign)[:2])
            print(
                f"  {name}: {int(m.sum())} rays, {np.unique(pas[m]).size} passes, off-normal {q(off[m])} deg, "
                f"range {q(rng[m])} m; error along {e[:2] @ normal:+.2f} across {e[:2] @ np.array([normal[1], -normal[0]]):+.2f} m, up {e[2]:+.2f}; "
                f"plain least squares {plain[False]:.2f} m, with box ranges {plain[True]:.2f} m (box range / true median {np.median(box_r[m][box_r[m] > 0] / rng[m][box_r[m] > 0]):.3f}, {int((box_r[m] > 0).sum())} ranged)"
            )


if __name__ == "__main__":
    ids = [int(s) for s in sys.argv[4].split(",")]
    main(
        sys.argv[1],
        int(sys.argv[2]),
        int(sys.argv[3]),
        ids,
        sys.argv[5] if len(sys.argv) > 5 else "",
    )
