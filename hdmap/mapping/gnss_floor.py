"""The covariance floor of a landmark: the GNSS error that more passes do not average away.

Passes of a fleet's receivers at one place share part of their position error: a receiver
type's bias, what lasts longer than a pass and recurs (issue #18 point 5). The
cluster-robust covariance (:mod:`hdmap.mapping.estimator.solve`) measures only what
varies from pass to pass, so it shrinks as ``1/G`` past the shared part. This module
measures that part from a truth-referenced error log (receiver fix minus an RTK truth,
per epoch; ``D`` drives, each one receiver over many minutes):

- per drive ``d`` its long-run mean error ``m_d`` (what its passes share however many);
- the mean's sampling variance ``V_d`` by batch means: the drive cut into ``B`` batches of
  ``batch_s`` seconds (longer than the error's correlation time), ``V_d = S_b^2 / B``
  with ``S_b^2`` the batches' sample covariance;
- the floor ``F = (1/D) sum_d (m_d m_d^T - V_d)``, projected onto the positive
  semi-definite cone (negative eigenvalues to 0): the second moment of a receiver's true
  long-run mean, ``E[m m^T]``, unbiased before the projection (``E[m^ m^^T] = m m^T + V``).

``F`` is what a landmark passed only by receivers like the logged ones keeps however many
passes it has; it is added to the published covariance (``SolverConfig.shared_floor_m2``).
With many receivers of several kinds at a landmark the shared part is the mean of their
means, smaller: ``F`` is then conservative. A log with independent per-pass errors (the
simulator's receiver) gives ``F`` near 0.

Pitfall: ``F`` comes from ``D`` drives, often one or two: it is a point estimate with
``D`` degrees of freedom, reported with ``drives`` so that a reader can judge it.

>>> rng = np.random.default_rng(0)
>>> t = np.arange(3600.0)
>>> biased = np.column_stack([0.5 + rng.normal(0, 0.3, 3600), rng.normal(0, 0.3, 3600)])
>>> f = shared_floor([t], [biased])
>>> bool(abs(f.cov[0, 0] - 0.25) < 0.01 and abs(f.cov[1, 1]) < 0.01)
True
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SharedFloor:
    """The floor and what it was measured from."""

    cov: Array
    """(k, k) floor covariance, m^2 (k = the error columns: East, North[, Up])."""
    drive_means: Array
    """(D, k) each drive's mean error, m."""
    mean_variances: Array
    """(D, k, k) each mean's batch-means sampling variance, m^2."""
    batches: tuple[int, ...]
    """Batches per drive."""

    @property
    def drives(self) -> int:
        return int(self.drive_means.shape[0])

    @property
    def sigma(self) -> Array:
        """Per column, the floor's standard deviation, m."""
        return np.sqrt(np.diag(self.cov))


def batch_means(t: Array, err: Array, batch_s: float) -> Array:
    """(B, k) mean error of each ``batch_s`` window of a drive (``t`` seconds, increasing;
    windows from the first epoch, empty ones left out)."""
    t = np.asarray(t, float)
    e = np.asarray(err, float).reshape(len(t), -1)
    idx = np.floor((t - t[0]) / batch_s).astype(np.int64)
    uniq, inv = np.unique(idx, return_inverse=True)
    sums = np.zeros((uniq.size, e.shape[1]))
    np.add.at(sums, inv, e)
    return sums / np.bincount(inv)[:, None]


def shared_floor(
    times: Sequence[Array], errors: Sequence[Array], batch_s: float = 300.0, min_batches: int = 3
) -> SharedFloor:
    """The floor of the module docstring from drives ``errors[d]`` ((n_d, k) fix minus
    truth, m) at ``times[d]`` (s). A drive shorter than ``min_batches`` batches counts its
    mean with the variance of its epochs over their count (white errors assumed: an
    optimistic ``V_d``, so a larger floor)."""
    if len(times) != len(errors) or not errors:
        raise ValueError("shared_floor: one time array per drive, at least one drive")
    means, variances, nb = [], [], []
    for t, e in zip(times, errors, strict=True):
        e = np.asarray(e, float).reshape(len(t), -1)
        if not np.isfinite(e).all() or len(e) < 2:
            raise ValueError("shared_floor: every drive needs at least 2 finite errors")
        b = batch_means(np.asarray(t, float), e, batch_s)
        if len(b) >= min_batches:
            v = np.atleast_2d(np.cov(b.T)) / len(b)
        else:
            v = np.atleast_2d(np.cov(e.T)) / len(e)
        means.append(e.mean(axis=0))
        variances.append(v)
        nb.append(len(b))
    m = np.array(means)
    v = np.array(variances)
    second = np.einsum("di,dj->ij", m, m) / len(m) - v.mean(axis=0)
    return SharedFloor(psd_part(second), m, v, tuple(nb))


def psd_part(c: Array) -> Array:
    """The symmetric positive semi-definite matrix nearest ``c`` (Frobenius): its
    negative eigenvalues set to 0.

    >>> psd_part(np.array([[1.0, 0.0], [0.0, -1.0]])).tolist()
    [[1.0, 0.0], [0.0, 0.0]]
    """
    s = 0.5 * (np.asarray(c, float) + np.asarray(c, float).T)
    lam, vec = np.linalg.eigh(s)
    return (vec * np.maximum(lam, 0.0)) @ vec.T


def floor_enu(f: SharedFloor) -> Array:
    """(3, 3) ENU floor from a 2-column (East, North) or 3-column floor; Up 0 if not logged."""
    k = f.cov.shape[0]
    if k not in (2, 3):
        raise ValueError(f"floor_enu: 2 or 3 error columns, got {k}")
    out = np.zeros((3, 3))
    out[:k, :k] = f.cov
    return out


def shared_floor_m2(f: SharedFloor) -> list[float]:
    """The ENU floor (:func:`floor_enu`) as ``SolverConfig.shared_floor_m2``: the wire's
    covariance order (ee, en, eu, nn, nu, uu), m^2."""
    c = floor_enu(f)
    return [float(c[i, j]) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
