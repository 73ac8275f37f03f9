"""Landmark estimator: bias-compensated incremental normal-equation sums, pass-level
(cluster-robust) sandwich covariance, gating statistic and initialiser. Pure maths, no I/O.

See ``docs/estimator.md`` for the model, the derivations and the measured behaviour.

>>> import numpy as np
>>> from hdmap.geo.geodesy import direction_from_angles
>>> rng = np.random.default_rng(0)
>>> x_true = np.array([5.0, 0.0, 2.5])
>>> sums = LandmarkSums(EstimatorConfig())
>>> row = sums.new_rows(1, [[6.0, 3.0, 2.0]])
>>> for p in range(60):   # 60 passes of 8 rays each, 0.1 rad azimuth noise
...     a = np.stack([np.full(8, 0.5), np.linspace(-40, -10, 8), np.full(8, 1.4)], 1)
...     a_meas = a + rng.normal(0, 1.0, a.shape)
...     v = x_true - a
...     az = np.arctan2(v[:, 0], v[:, 1]) + rng.normal(0, 0.1, 8)
...     el = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1])) + rng.normal(0, 0.005, 8)
...     rays = Rays.from_angles(a_meas, az, el, 0.1, 0.005, 1.0, 1.0)
...     sums.accumulate(np.repeat(row, 8), np.full(8, p), rays)
...     sol = sums.solve(row)
>>> bool(sol.ok[0]), bool(np.linalg.norm(sol.x[0, :2] - x_true[:2]) < 2.0)
(True, True)
"""

from hdmap.mapping.estimator.gating import (
    angle_jacobian,
    excess_angular_variance,
    ray_chi2,
    triangulate,
    wrap,
)
from hdmap.mapping.estimator.model import (
    EstimatorConfig,
    Rays,
    projector_terms,
    ray_angles,
    weights,
)
from hdmap.mapping.estimator.solve import Solution, hotelling_inflation, solve_sums
from hdmap.mapping.estimator.sums import LandmarkSums
from hdmap.mapping.estimator.terms import ray_terms

__all__ = [
    "EstimatorConfig",
    "LandmarkSums",
    "Rays",
    "Solution",
    "angle_jacobian",
    "excess_angular_variance",
    "hotelling_inflation",
    "projector_terms",
    "ray_angles",
    "ray_chi2",
    "ray_terms",
    "solve_sums",
    "triangulate",
    "weights",
    "wrap",
]
