"""The solver's shared-error floor (``SolverConfig.shared_floor_m2``) and confirmation limit
(``confirm_max_sigma_m``). The floor is added to the published
covariance in the landmark's local ENU, the estimate unchanged; a floor that is not a
covariance is refused naming the field. In-process services on real SQLite (scene of
tests/support/services.py: one sign, passes driving north)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hdmap.runtime.config import ConfigError, from_mapping
from schemas import STATUS_CANDIDATE, STATUS_CONFIRMED
from services.solver.service import SolverConfig
from tests.support.services import (
    SIGN,
    one_sign_solver,
    updates,
)

FLOOR = (0.09, -0.25, 0.0, 0.70, 0.0, 0.0)
"""The GSDC phones' floor (hdmap/mapping/gnss_floor.py on fleetsim/data), rounded."""


def published(tmp: Path, cfg: SolverConfig, passes: int = 8):
    start = SIGN + np.array([0.4, -0.3, 0.0])
    return updates(one_sign_solver(tmp, cfg, passes, start))[-1].landmarks


def test_the_floor_is_added_to_the_published_covariance_and_nothing_else(tmp_path: Path):
    base = published(tmp_path / "a", SolverConfig())
    floored = published(tmp_path / "b", SolverConfig(shared_floor_m2=FLOOR))
    assert len(base) == len(floored) == 1
    np.testing.assert_array_equal(floored.lat, base.lat)
    np.testing.assert_array_equal(floored.lon, base.lon)
    np.testing.assert_allclose(floored.cov - base.cov, np.array([FLOOR]), atol=1e-12)


def test_a_floor_that_is_not_a_covariance_is_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"solver\.shared_floor_m2: not positive semi-definite"):
        SolverConfig(shared_floor_m2=(1.0, 2.0, 0.0, 1.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match=r"solver\.shared_floor_m2: six finite numbers"):
        from_mapping(SolverConfig, {"shared_floor_m2": [1.0, 0.0]}, "solver")
    with pytest.raises(ConfigError, match="shared_floor_m2"):
        SolverConfig(shared_floor_m2=(float("nan"), 0.0, 0.0, 1.0, 0.0, 0.0))


def test_a_landmark_is_confirmed_only_while_its_position_is_known_to_the_limit(tmp_path: Path):
    """Confirmed with its own covariance (sub-metre here); the same landmark with 3 m of
    floor East (sigma above ``confirm_max_sigma_m`` = 2 m) is published as a candidate,
    estimate and covariance unchanged; with no limit, confirmed again."""
    wide = (9.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    n = 30
    base = published(tmp_path / "a", SolverConfig(), n)
    vague = published(tmp_path / "b", SolverConfig(shared_floor_m2=wide), n)
    free = published(
        tmp_path / "c", SolverConfig(shared_floor_m2=wide, confirm_max_sigma_m=np.inf), n
    )

    def sigma_major(lm) -> float:  # the larger horizontal sigma, as the solver reads it
        c = lm.cov[0]
        return float(np.sqrt(np.linalg.eigvalsh([[c[0], c[1]], [c[1], c[3]]])[-1]))

    assert sigma_major(base) < 2.0 < sigma_major(vague)
    assert base.status.tolist() == [STATUS_CONFIRMED]
    assert vague.status.tolist() == [STATUS_CANDIDATE]
    assert free.status.tolist() == [STATUS_CONFIRMED]
    np.testing.assert_array_equal(vague.lat, base.lat)
    np.testing.assert_allclose(vague.cov - base.cov, np.array([wide]), atol=1e-12)
    with pytest.raises(ConfigError, match=r"solver\.confirm_max_sigma_m"):
        SolverConfig(confirm_max_sigma_m=0.0)


def test_the_pass_correlation_scales_the_between_pass_covariance(tmp_path: Path):
    """``pass_correlation`` kappa: the covariance before the per-axis floor is multiplied by
    ``1 + kappa G`` (G the landmark's passes), the estimate unchanged."""
    none = SolverConfig(systematic_sigma_m=(0.0, 0.0, 0.0))
    base = published(tmp_path / "a", none)
    corr = published(tmp_path / "b", replace(none, pass_correlation=0.05))
    np.testing.assert_array_equal(corr.lat, base.lat)
    g = float(base.n_passes[0])
    assert g == 8
    np.testing.assert_allclose(corr.cov, base.cov * (1 + 0.05 * g), rtol=1e-9)


def test_a_bad_pass_correlation_or_systematic_sigma_is_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"solver\.pass_correlation"):
        SolverConfig(pass_correlation=-0.01)
    with pytest.raises(ConfigError, match=r"solver\.pass_correlation"):
        from_mapping(SolverConfig, {"pass_correlation": float("inf")}, "solver")
    with pytest.raises(ConfigError, match=r"solver\.systematic_sigma_m"):
        SolverConfig(systematic_sigma_m=(0.1, -0.1, 0.1))
