"""A landmark's own panel scale in the range test (``GateConfig.landmark_scale``).

Two same-class panels on one line of sight, 4 m apart: the bearings cannot tell them
apart, the box ranges can only once each landmark's panel scale is known. A box range is
the distance a panel of the class's nominal size would be at; a panel 10 % small looks
10 % farther than it is, so against the catalogue's spread alone (10 %, what every ray's
``sigma_range_m`` carries) the near small panel's rays fit the far landmark as well as
their own.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap.geo.signs import DEFAULT_SIZE_REL_SIGMA
from hdmap.mapping.association import GateConfig, LocalRays
from hdmap.mapping.batch_association import UnitInput, associate_units

WHITE_REL = 0.03
"""The box's own relative range noise the rays claim besides the catalogue's spread."""


def rays_at(dist: np.ndarray, scale: float) -> LocalRays:
    """Rays from the origin looking North at a panel ``dist`` metres away whose real size
    is ``scale`` times its class's nominal size (box ranges ``dist / scale``), one image
    each."""
    n = dist.size
    r = dist / scale
    return LocalRays(
        origin=np.zeros((n, 3)),
        direction=np.tile([0.0, 1.0, 0.0], (n, 1)),
        sigma_az=np.full(n, 0.002),
        sigma_el=np.full(n, 0.002),
        sigma_pos_h=np.full(n, 0.1),
        sigma_pos_v=np.full(n, 0.1),
        range_m=r,
        sigma_range_m=r * np.hypot(WHITE_REL, DEFAULT_SIZE_REL_SIGMA),
        image=np.arange(n, dtype=np.int64),
        sign_class=np.full(n, 7, np.int64),
    )


# the near panel 10 % small at 20 m, a full-size one 4 m behind it on the same bearing
X = np.array([[0.0, 20.0, 0.0], [0.0, 24.0, 0.0]])
COV = np.tile(np.eye(3) * 0.01, (2, 1, 1))
CLS = np.array([7, 7], np.int64)
SCALES = np.array([0.9, 1.0])
CFG = GateConfig(pass_bias_sigma_m=0.3, vertical_bias_sigma_m=0.3, min_offset_rays=99)


def linked(rays: LocalRays, scale: np.ndarray | None, mode: str) -> np.ndarray:
    unit = UnitInput(rays, X, COV, CLS, None, scale)
    return associate_units([unit], replace(CFG, landmark_scale=mode))[0].landmark


@pytest.mark.parametrize("mode", ["cost", "both"])
def test_the_landmarks_scale_tells_panels_on_one_bearing_apart(mode: str) -> None:
    near = rays_at(np.array([20.0]), 0.9)  # box range 22.2 m: nearer the far landmark
    assert linked(near, None, mode).tolist() == [1]  # scales unknown: the far one
    assert linked(near, SCALES, "off").tolist() == [1]
    assert linked(near, SCALES, mode).tolist() == [0]
    far = rays_at(np.array([24.0]), 1.0)
    assert linked(far, SCALES, mode).tolist() == [1]


def test_an_unknown_scale_keeps_the_catalogues_spread() -> None:
    near = rays_at(np.array([20.0]), 0.9)
    assert linked(near, np.array([np.nan, np.nan]), "both").tolist() == [1]
    # known for the far landmark only: the near ray's 22.2 m box range is 8 % short of
    # it, about two of its sharp sigmas; its own landmark still takes it on the spread
    assert linked(near, np.array([np.nan, 1.0]), "both").tolist() == [0]


def test_the_gate_refuses_a_range_its_scale_rules_out() -> None:
    """With ``both`` a ray whose box range its only candidate's scale puts 20 % off is
    not linked; with ``cost`` the catalogue's spread still admits it."""
    x, cov, cls = X[1:], COV[1:], CLS[1:]
    ray = rays_at(np.array([24.0]), 1.2)  # a panel 20 % larger: box range 20 m
    for mode, want in (("cost", [0]), ("both", [-1]), ("off", [0])):
        unit = UnitInput(ray, x, cov, cls, None, np.array([1.0]))
        got = associate_units([unit], replace(CFG, landmark_scale=mode, chi2_gate=1e6))
        assert got[0].landmark.tolist() == want, mode


def test_the_spread_taken_out_is_the_configured_one() -> None:
    """The rays' range sigmas hold the catalogue's spread; what is left with the scale
    known is the box's own noise. Told the spread is 5 % (not the 10 % they hold), the
    gate leaves the ray sigma^2 - 5^2 % of white noise (8.7 %) and admits the 20 % ray
    that the default's 3 % refuses."""
    x, cov, cls = X[1:], COV[1:], CLS[1:]
    ray = rays_at(np.array([24.0]), 1.2)
    unit = UnitInput(ray, x, cov, cls, None, np.array([1.0]))
    gate = replace(CFG, landmark_scale="both", chi2_gate=1e6)
    assert associate_units([unit], gate)[0].landmark.tolist() == [-1]
    assert associate_units([unit], gate, 0.05)[0].landmark.tolist() == [0]
