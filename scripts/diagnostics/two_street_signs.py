"""Signs seen from two streets, or head-on down one: where their true rays put them.

Usage: python scripts/diagnostics/two_street_signs.py GNSS PASSES SEED SIGN_ID[,SIGN_ID...]
[KNOB=V,...] (from ``scripts/diagnostics/``; ``GNSS`` and the ``EstimatorConfig`` knobs as in
``true_association_fleet.py``). For each sign: its true rays over the fleet evaluation's
passes, all together and split by viewing azimuth into those within 30 degrees of the
sign's facing and the rest; each solved on its own in ``LandmarkSums`` and by plain
weighted least squares, bearings only and with the rays' box ranges. Printed per part:
rays, passes, viewing angle off the sign's normal and range quartiles, the
``LandmarkSums`` error along / across the sign's facing normal (positive: in front of
it), the two plain errors.

Pitfall: the split is by ray, so one pass's view of a sign near the 30-degree line falls
in both parts, each with a fraction of the pass's parallax, and a part solved alone is
then far worse than the sign is. Seed 0's sign 167 (seen from 42-58 m, 25-34 degrees off
its normal), 400 passes, white heading noise only (``white:0.57``): its two parts come out
4.0 and 5.0 m beyond it (2.2 and 1.6 m without the pass weights, 1.2 and 5.4 m in front
without the bias compensation), all its rays together 0.4 m; with FLEET's noise 0.65 m
(docs/experiments/2026-12-line-of-sight-mixture.md).
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import dataclass
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

RAY_FIELDS = ("origin", "direction", "sigma_az", "sigma_el", "sigma_pos_h", "sigma_pos_v")


def take(rays: Rays, m: np.ndarray) -> Rays:
    """The rays ``m`` (indices or mask), unweighted."""
    return Rays(*(np.asarray(getattr(rays, f))[m] for f in RAY_FIELDS), None)


@dataclass
class SignRays:
    """One sign's true rays over the passes (world frame), with their box ranges."""

    rays: list[Rays]
    passes: list[np.ndarray]
    box_r: list[np.ndarray]
    box_s: list[np.ndarray]

    def joined(self) -> tuple[Rays, np.ndarray, np.ndarray, np.ndarray]:
        rays = Rays(*(np.concatenate([getattr(r, k) for r in self.rays]) for k in RAY_FIELDS))
        return rays, *(np.concatenate(v) for v in (self.passes, self.box_r, self.box_s))


def plain_lsq(rays: Rays, box_r: np.ndarray | None, box_s: np.ndarray) -> np.ndarray:
    """Textbook weighted least squares of the rays (perpendicular distances, the angular
    sigma at 40 m), with each box range as a ``d . x = d . a + r`` term if given (weight
    ``1 / (sigma_r^2 + sigma_h^2)``)."""
    o, d = rays.origin, rays.direction
    s_h = np.asarray(rays.sigma_pos_h, float)
    w = 1.0 / (s_h**2 + (40.0 * np.asarray(rays.sigma_az, float)) ** 2)
    dd = np.einsum("ni,nj->nij", d, d)
    p = np.eye(3)[None] - dd
    a_mat = np.einsum("n,nij->ij", w, p)
    b_vec = np.einsum("n,nij,nj->i", w, p, o)
    if box_r is not None:
        wr = np.where(box_r > 0, 1.0 / (box_s**2 + s_h**2), 0.0)
        a_mat += np.einsum("n,nij->ij", wr, dd)
        b_vec += np.einsum("n,ni->i", wr * (np.einsum("ni,ni->n", d, o) + box_r), d)
    return np.linalg.solve(a_mat, b_vec)


def collect(world, fleet, model, n_passes: int, rows: np.ndarray) -> dict[int, SignRays]:
    """Per sign row: its true rays of the first ``n_passes`` passes."""
    got = {int(r): SignRays([], [], [], []) for r in rows}
    with tempfile.TemporaryDirectory() as queue:
        agent = VehicleAgent("veh-0001", model, queue)
        for k, p in enumerate(fleet.passes(n_passes)):
            obs = agent.record(p.pass_id, p.fixes, p.detections)
            seen = true_rays(world, agent, p, obs)
            if seen is None:
                continue
            rays, r = seen
            sid = p.truth.sign_id[agent.last_kept]
            ok = (sid >= 0) & (world.signs.index_of(sid) >= 0)
            box_r, box_s = np.asarray(obs.range_m)[ok], np.asarray(obs.sigma_range_m)[ok]
            for row, acc in got.items():
                m = np.flatnonzero(r == row)
                if m.size:
                    acc.rays.append(take(rays, m))
                    acc.passes.append(np.full(m.size, k))
                    acc.box_r.append(box_r[m])
                    acc.box_s.append(box_s[m])
        agent.close()
    return got


def report(world, row: int, acc: SignRays, est: EstimatorConfig) -> None:
    sign = world.signs.position[row]
    face = np.radians(world.signs.facing_azimuth_deg[row])
    normal = np.array([np.sin(face), np.cos(face)])
    across_dir = np.array([normal[1], -normal[0]])
    rays, pas, box_r, box_s = acc.joined()
    d = rays.direction
    view = np.degrees(np.arctan2(-d[:, 0], -d[:, 1]))
    off = (view - np.degrees(face) + 180.0) % 360.0 - 180.0
    rng = np.linalg.norm(sign[:2] - rays.origin[:, :2], axis=1)
    print(
        f"sign {int(world.signs.id[row])} (class {world.signs.sign_class[row]}, facing "
        f"{np.degrees(face) % 360:.0f} deg): {len(rays)} rays, {np.unique(pas).size} passes"
    )
    parts = (
        ("all", np.ones(off.shape, bool)),
        ("near facing", np.abs(off) <= 30.0),
        ("oblique", np.abs(off) > 30.0),
    )
    for name, m in parts:
        if m.sum() < 5:
            print(f"  {name}: {int(m.sum())} rays")
            continue
        part = take(rays, m)
        sums = LandmarkSums(est)
        lm = sums.new_rows(1, sign[None] + np.array([1.0, 1.0, 0.0]))
        sums.accumulate(np.repeat(lm, int(m.sum())), pas[m].astype(np.int64), part)
        e = sums.solve(lm).x[0] - sign
        plain = [np.hypot(*(plain_lsq(part, r, box_s[m]) - sign)[:2]) for r in (None, box_r[m])]
        ranged = box_r[m] > 0
        ratio = np.median(box_r[m][ranged] / rng[m][ranged]) if ranged.any() else np.nan

        def q(a: np.ndarray) -> list[float]:
            return np.percentile(a, [25, 50, 75]).round(1).tolist()

        print(
            f"  {name}: {int(m.sum())} rays, {np.unique(pas[m]).size} passes, off the normal "
            f"{q(off[m])} deg, range {q(rng[m])} m; error along {e[:2] @ normal:+.2f} across "
            f"{e[:2] @ across_dir:+.2f} up {e[2]:+.2f} m; plain least squares {plain[0]:.2f} m, "
            f"with box ranges {plain[1]:.2f} m ({int(ranged.sum())} ranged, box range over "
            f"true range median {ratio:.3f})"
        )


def main(which: str, n_passes: int, seed: int, ids: list[int], overrides: str = "") -> None:
    knobs = {k: float(v) for k, v in (kv.split("=") for kv in overrides.split(",") if kv)}
    est = EstimatorConfig(
        **{k: type(getattr(EstimatorConfig(), k))(float(v)) for k, v in knobs.items()}
    )
    noise = noise_for(which)
    cfg = FleetEvalConfig(Path(tempfile.gettempdir()), seed=seed)
    world = evaluation_world(cfg)
    model = model_for(noise, load_vehicle_model())
    fleet_cfg = FleetConfig(n_vehicles=cfg.vehicles, route_length_m=(600.0, 1200.0))
    fleet = Fleet(world, model, noise, fleet_cfg, seed)
    got = collect(world, fleet, model, n_passes, world.signs.index_of(np.array(ids)))
    for row, acc in got.items():
        if acc.rays:
            report(world, row, acc, est)


if __name__ == "__main__":
    argv = sys.argv[1:]
    ids = [int(s) for s in argv[3].split(",")]
    main(argv[0], int(argv[1]), int(argv[2]), ids, argv[4] if len(argv) > 4 else "")
