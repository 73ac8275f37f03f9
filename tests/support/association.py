"""Association scenes: rays from origins to points with stated noise."""

from __future__ import annotations

import numpy as np

from hdmap.geo.geodesy import direction_from_angles
from hdmap.mapping.association import (
    LocalRays,
    angles,
)


def rays_to(
    points: np.ndarray,
    origins: np.ndarray,
    rng,
    s_ang=0.01,
    s_pos=1.0,
    bias=None,
    images=None,
    cls=4,
    ranged=True,
) -> LocalRays:
    """Noisy rays from origins toward points (angles perturbed, origins perturbed)."""
    n = len(origins)
    true_a = origins.copy()
    noisy_a = true_a + rng.normal(0, s_pos, (n, 3))
    if bias is not None:
        noisy_a = noisy_a + bias
    az, el = angles(points - true_a)
    d = direction_from_angles(az + rng.normal(0, s_ang, n), el + rng.normal(0, s_ang, n))
    rng_m = np.linalg.norm(points - true_a, axis=1)
    return LocalRays(
        origin=noisy_a,
        direction=d,
        sigma_az=np.full(n, s_ang),
        sigma_el=np.full(n, s_ang),
        sigma_pos_h=np.full(n, s_pos),
        sigma_pos_v=np.full(n, s_pos),
        range_m=rng_m * (1 + rng.normal(0, 0.05, n)) if ranged else np.zeros(n),
        sigma_range_m=0.1 * rng_m if ranged else np.zeros(n),
        image=np.arange(n) if images is None else images,
        sign_class=np.full(n, cls),
    )
