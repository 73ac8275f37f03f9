"""Where one sign's rays go, unit by unit, and why: a finished fleet evaluation's uploads
replayed (``replay_ab.py``) with the matcher's association recorded per unit
(docs/experiments/2026-12-group-check-by-track.md).

Usage: python scripts/diagnostics/unit_fates.py RUN_DIR SEED SIGN [NEAR_M] [gnss=gsdc]
[KEY=JSON ...]
``RUN_DIR/seed-SEED`` is one seed's output of ``hdmap eval fleet --out RUN_DIR`` (its
``run/truth.npz`` gives every observation's true sign). For each unit holding rays of sign
``SIGN`` taken within ``NEAR_M`` (default 30) metres of it, the rays' fate: all linked to
the sign's landmark (a candidate within 3 m of the sign), all unlinked, or mixed; for the
unlinked, whether the association had given them to the sign's landmark before the group
check took them back, and what that group held (other signs' rays, tracks). ``KEY=JSON``
sets a ``MatcherConfig`` field as in ``replay_ab.py``.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np
import replay_ab
from landmark_pairs import true_signs

import hdmap.mapping.unit as unit_mod
import services.matcher.service as matcher_service
from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world

OWN_M = 3.0
"""A candidate of the sign's class within this horizontal distance of it is the sign's
landmark (under the evaluation's 5 m pairing radius, so that a mixture 4-5 m off, as seed
0's 99/167, is not counted as the sign's)."""


def fate(rec: dict) -> list[str]:
    """The outcome lines of one unit's near rays (``rec``: what :func:`recorder` kept)."""
    sel, own = rec["sel"], rec["own"]
    if rec["landmark"] is None:
        return ["no candidate"]
    if not own.size:
        return ["no landmark of the sign among the candidates"]
    m, a = rec["matched"][sel], rec["landmark"][sel]
    if np.isin(m, own).all():
        return ["all linked to the sign's landmark"]
    kind = "all unlinked" if (m < 0).all() else "mixed"
    out = [kind]
    given = np.isin(a, own)
    if (given & (m < 0)).any():
        grp = np.isin(rec["landmark"], own) & (rec["cls"] == rec["sign_class"])
        others = bool((rec["lab"][grp] != rec["sign"]).any())
        out.append(f"{kind}: group check took back the sign's group")
        out.append(
            f"  its group: {np.unique(rec['track'][grp]).size} track(s), "
            f"other signs' rays {'yes' if others else 'no'}"
        )
    elif (a < 0).all():
        out.append(f"{kind}: not gated to any candidate")
    else:
        out.append(f"{kind}: given to another landmark")
    return out


def recorder(key: dict, world, sign: int, near_m: float, recs: dict):
    """``unit.associate_prepared`` wrapped to keep, per unit with near rays of ``sign``,
    the rays' true signs, the candidates near the sign and the association."""
    k = world.signs.index_of(np.array([sign]))[0]
    p, cls = world.signs.position[k], int(world.signs.sign_class[k])
    inner = unit_mod.associate_prepared

    def wrapped(m, units):
        res = inner(m, units)
        for u, chk in zip(units, res, strict=True):
            lab = np.array([key.get((u.vehicle, int(o)), -9) for o in u.obs.obs_id.tolist()])
            a = world.frame.from_geodetic(u.obs.lat, u.obs.lon, u.obs.h).reshape(-1, 3)
            sel = (lab == sign) & (np.linalg.norm(a - p, axis=1) < near_m)
            if not sel.any():
                continue
            cx = world.frame.from_ecef(np.array([c.x for c in u.cands]).reshape(-1, 3))
            same = np.array([c.cls == cls for c in u.cands], bool)
            own = np.flatnonzero(same & (np.linalg.norm(cx[:, :2] - p[:2], axis=1) < OWN_M))
            recs[(u.vehicle, u.pass_id, u.tile, int(u.obs.obs_id[0]))] = dict(
                lab=lab,
                sel=sel,
                own=own,
                cls=u.rays.sign_class,
                track=u.rays.tracks,
                sign=sign,
                sign_class=cls,
                landmark=None if chk is None else chk.res.landmark,
                matched=None if chk is None else chk.matched,
            )
        return res

    return wrapped


def main(root: Path, seed: int, sign: int, args: list[str]) -> None:
    near_m = float(args.pop(0)) if args and "=" not in args[0] else 30.0
    gnss = next((a.partition("=")[2] for a in args if a.startswith("gnss=")), "fleet")
    key = true_signs(root / f"seed-{seed}" / "run")
    world = evaluation_world(FleetEvalConfig(out=Path("/tmp"), seed=seed, gnss=gnss))
    recs: dict = {}
    wrapped = recorder(key, world, sign, near_m, recs)
    unit_mod.associate_prepared = wrapped  # type: ignore[assignment]
    matcher_service.associate_prepared = wrapped  # type: ignore[assignment]
    replay_ab.main(root, seed, args)
    tally = Counter(line for rec in recs.values() for line in fate(rec))
    print(f"units with rays of sign {sign} within {near_m:g} m: {len(recs)}")
    for line, n in sorted(tally.items()):
        print(f"{n:6d}  {line}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4:])
