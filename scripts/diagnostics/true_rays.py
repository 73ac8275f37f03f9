"""Shared by the diagnostics: a pass's observations that saw a true sign, as ``Rays`` in
the world frame, with the rows of the signs they saw."""

from __future__ import annotations

import numpy as np

from hdmap.mapping.estimator import Rays


def true_rays(world, agent, p, obs) -> tuple[Rays, np.ndarray] | None:
    """The rays of ``obs`` (what ``agent`` just recorded of pass ``p``) that saw a true
    sign, with their box ranges, and per ray the sign's row in ``world.signs``; None if
    there are none."""
    sid = p.truth.sign_id[agent.last_kept]
    r = world.signs.index_of(sid)
    ok = (sid >= 0) & (r >= 0)
    if not ok.any():
        return None
    rays = Rays(
        world.frame.from_geodetic(obs.lat, obs.lon, obs.h)[ok],
        np.asarray(obs.direction)[ok],
        np.asarray(obs.sigma_az)[ok],
        np.asarray(obs.sigma_el)[ok],
        np.asarray(obs.sigma_pos_h)[ok],
        np.asarray(obs.sigma_pos_v)[ok],
        None,
        np.asarray(obs.range_m, float)[ok],
        np.asarray(obs.sigma_range_m, float)[ok],
    )
    return rays, r[ok]
