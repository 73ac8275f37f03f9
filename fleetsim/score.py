"""Score a map against the simulator's ground truth.

True signs and estimated landmarks are paired one-to-one by class and horizontal
distance (:func:`fleetsim.truth.match_map`, pairs farther than ``max_dist_m`` not
allowed; confirmed landmarks before candidates).

- found: true signs with a landmark; missed: eligible true signs without one;
- duplicated: unpaired landmarks within ``max_dist_m`` of a paired true sign of
  their class (a second copy of a sign); false: the other unpaired landmarks;
- horizontal error of each pair, and whether the truth lies inside the reported
  95% region: the 2D chi-square ellipse (e^T C^-1 e <= 5.991 on the horizontal
  block of the covariance) and, as in the paper, East and North within +/-2 sigma.

>>> import numpy as np
>>> from scipy.stats import chi2
>>> round(float(chi2.ppf(0.95, 2)), 3)
5.991
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from fleetsim.truth import LandmarkMatch, match_map
from fleetsim.world import World
from schemas import Landmarks

CHI2_95_2D = 5.991464547107979


@dataclass(frozen=True)
class MapScore:
    n_true: int
    n_eligible: int
    n_landmarks: int
    found: int
    missed: int
    duplicated: int
    false: int
    mean_err_m: float
    p95_err_m: float
    coverage95: float
    """Share of paired landmarks whose truth is inside the 2D chi-square 95% ellipse."""
    coverage_en: float
    """Share with East and North errors both within +/-2 sigma (the paper's band)."""

    def as_dict(self) -> dict:
        return asdict(self)


def cov_en(cov6: NDArray) -> NDArray:
    """(n, 6) ENU covariance (ee en eu nn nu uu) -> (n, 2, 2) East/North block."""
    c = np.asarray(cov6, float).reshape(-1, 6)
    return np.stack([np.stack([c[:, 0], c[:, 1]], -1), np.stack([c[:, 1], c[:, 3]], -1)], -2)


def inside_ellipse95(err_en: NDArray, cov6: NDArray) -> NDArray[np.bool_]:
    """Whether each East/North error lies inside the 2D chi-square 95% ellipse of its
    covariance ((n, 6) ENU as on the wire).

    >>> inside_ellipse95(np.array([[1.0, 0.0], [3.0, 0.0]]), np.array([[1.0, 0, 0, 1, 0, 1]] * 2))
    array([ True, False])
    """
    c = cov_en(cov6)
    e = np.asarray(err_en, float).reshape(-1, 2)
    m2 = np.einsum("ki,kij,kj->k", e, np.linalg.inv(c + 1e-12 * np.eye(2)), e)
    return m2 <= CHI2_95_2D


def duplicate_mask(
    world: World, lm: Landmarks, m: LandmarkMatch, max_dist_m: float
) -> NDArray[np.bool_]:
    """Per landmark: unpaired, yet within ``max_dist_m`` of a paired true sign of its class
    (a second copy of a sign)."""
    dup = np.zeros(len(lm), bool)
    if not m.spurious.size:
        return dup
    signs = world.signs
    taken = np.zeros(len(signs), bool)
    taken[m.sign_row] = True
    est = world.frame.from_geodetic(lm.lat, lm.lon, lm.h).reshape(-1, 3)[m.spurious, :2]
    d = np.linalg.norm(est[:, None, :] - signs.position[None, :, :2], axis=-1)
    same = lm.sign_class[m.spurious][:, None] == signs.sign_class[None, :]
    dup[m.spurious] = (same & taken[None, :] & (d <= max_dist_m)).any(axis=1)
    return dup


def score(
    world: World,
    lm: Landmarks,
    eligible: NDArray | None = None,
    max_dist_m: float = 5.0,
) -> MapScore:
    """Found / missed / duplicated / false and accuracy of a map (see module doc)."""
    signs = world.signs
    n_true = len(signs)
    elig = np.ones(n_true, bool) if eligible is None else np.asarray(eligible, bool)
    m = match_map(world, lm, max_dist_m)
    paired_true = np.zeros(n_true, bool)
    paired_true[m.sign_row] = True
    dup = int(duplicate_mask(world, lm, m, max_dist_m).sum())
    err_en = m.error_enu[:, :2]
    err_h = m.horizontal_error_m
    if err_h.size:
        c = cov_en(lm.cov)[m.landmark]
        sig = np.sqrt(np.stack([c[:, 0, 0], c[:, 1, 1]], -1))
        cov95 = float(np.mean(inside_ellipse95(err_en, lm.cov[m.landmark])))
        cov_band = float(np.mean(np.all(np.abs(err_en) <= 2 * sig, axis=1)))
        mean_err, p95 = float(err_h.mean()), float(np.percentile(err_h, 95))
    else:
        cov95 = cov_band = mean_err = p95 = float("nan")
    return MapScore(
        n_true=n_true,
        n_eligible=int(elig.sum()),
        n_landmarks=len(lm),
        found=int((paired_true & elig).sum()),
        missed=int((~paired_true & elig).sum()),
        duplicated=dup,
        false=int(m.spurious.size - dup),
        mean_err_m=mean_err,
        p95_err_m=p95,
        coverage95=cov95,
        coverage_en=cov_band,
    )
