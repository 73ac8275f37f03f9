"""Facing (:mod:`hdmap.mapping.facing`): the estimate against synthetic truth, the
association gate, and a corner of two same-class signs facing different streets through
an in-process matcher and solver (real SQLite, through their transactions).

Noise: viewing azimuths wrapped-normal around the truth (stated per test); the corner
scene has the matcher tests' pass bias (1 m per axis) and 0.01 rad angular noise.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binom
from scipy.stats import t as student_t

from fleetsim.synthetic import ray_observations
from hdmap.mapping.association import GateConfig, LocalRays
from hdmap.mapping.batch_association import associate
from hdmap.mapping.facing import (
    Facing,
    FacingConfig,
    angle_between,
    facing_from_sums,
    facings_compatible,
    ray_compatible,
    to_wire,
    view_vectors,
    viewing_azimuth,
)
from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry, ObsGroup
from schemas.map import updates_from_bytes
from services.matcher.service import MatcherConfig, MatcherService
from services.solver.service import SolverService
from tests.support.services import CLS, Sink, tile_of

T0 = 1.7e9


def directions_from(theta: np.ndarray) -> np.ndarray:
    """Camera-to-sign unit directions (level) whose viewing azimuth is ``theta``."""
    return np.stack([-np.sin(theta), -np.cos(theta), np.zeros_like(theta)], 1)


def test_viewing_azimuth_is_from_the_sign_toward_the_camera() -> None:
    # a camera south of the sign looks North: the sign is seen from the South (180 deg)
    d = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, -0.6, 0.8]])
    np.testing.assert_allclose(np.degrees(viewing_azimuth(d)), [180.0, 270.0, 0.0], atol=1e-12)
    theta = np.random.default_rng(0).uniform(0, 2 * np.pi, 50)
    np.testing.assert_allclose(viewing_azimuth(directions_from(theta)), theta, atol=1e-12)
    np.testing.assert_allclose(view_vectors(d)[2], [0.0, -1.0])


@pytest.mark.parametrize("s", [0.1, 0.5])
def test_facing_estimate_is_within_its_reported_sigma_of_the_truth(s: float) -> None:
    """n independent wrapped-normal azimuths of sigma ``s`` about ``mu`` (uniform), 400
    trials. The reported sigma is within 1 % of the delta-method standard error at
    s <= 0.5 rad (module docstring) and is itself estimated from the n angles, so the error
    over it is about Student's t with n - 1 dof: the count beyond its 97.5 % quantile is
    binomial(400, 0.05) (99.9 % bound), and the mean of z^2 is within 3.3 standard errors
    of t's E[z^2] = nu / (nu - 2) (Var z^2 = 3 nu^2 / ((nu-2)(nu-4)) - E[z^2]^2)."""
    rng = np.random.default_rng(7)
    trials, n = 400, 60
    z, spread = np.empty(trials), np.empty(trials)
    for k in range(trials):
        mu = rng.uniform(0, 2 * np.pi)
        theta = mu + rng.normal(0, s, n)
        f = facing_from_sums(view_vectors(directions_from(theta)).sum(0), [n], [n], 3)
        assert f.known[0] and 0 <= f.azimuth[0] < 2 * np.pi
        spread[k] = f.spread[0]
        err = (f.azimuth[0] - mu + np.pi) % (2 * np.pi) - np.pi
        z[k] = err / f.sigma[0]
    nu = n - 1
    assert int((np.abs(z) > student_t.ppf(0.975, nu)).sum()) <= binom.ppf(0.999, trials, 0.05)
    m2 = nu / (nu - 2)
    se = np.sqrt((3 * nu**2 / ((nu - 2) * (nu - 4)) - m2**2) / trials)
    assert abs(float(np.mean(z**2)) - m2) <= 3.3 * se
    # the spread estimates s: a sample sd of 60 has a relative sd of 1 / sqrt(120) = 0.09,
    # so the mean of 400 is within 4.5 standard errors (0.02) of s, with the O(1/n) bias
    assert abs(float(spread.mean()) / s - 1.0) < 0.02 + 1.0 / n


def test_sigma_counts_passes_not_rays_and_few_rays_give_no_facing() -> None:
    v = view_vectors(directions_from(np.radians([170.0, 180.0, 190.0, 200.0]))).sum(0)
    per_ray = facing_from_sums(v, [4], [4], 3)
    per_pass = facing_from_sums(v, [4], [1], 3)
    np.testing.assert_allclose(per_pass.sigma, per_ray.sigma * 2.0)
    assert np.degrees(per_ray.azimuth[0]) == pytest.approx(185.0, abs=1e-9)
    none = facing_from_sums(v[None] * 0.5, [2], [2], 3)
    assert not none.known[0] and none.sigma[0] == 0.0
    deg, sig = to_wire(Facing(*np.zeros((3, 2)), np.array([False, True])))
    assert deg.tolist() == [0.0, 0.0] and sig.tolist() == [0.0, 0.01]  # 0 = unknown only


def test_gate_refuses_the_other_street_and_keeps_the_cone() -> None:
    cfg = FacingConfig()
    west = Facing(np.radians([285.0]), np.radians([2.0]), np.radians([10.0]), np.array([True]))
    gate = cfg.max_view_deg + cfg.k_sigma * 2.0  # degrees
    theta = np.radians(285.0 + np.array([0.0, -60.0, 60.0, gate - 0.5, -gate + 0.5]))
    # a ray of the sign from its cone (within max_view + k sigma of its facing): kept
    assert ray_compatible(theta, west.take(np.zeros(5, int)), cfg).all()
    # just beyond, and the street 90 degrees round (seen from the South, 180-195): refused
    theta = np.radians(np.r_[285.0 + gate + 0.5, 285.0 - gate - 0.5, 180.0, 195.0, 105.0])
    assert not ray_compatible(theta, west.take(np.zeros(5, int)), cfg).any()
    unknown = Facing(*np.zeros((3, 1)), np.array([False]))
    assert ray_compatible(theta, unknown.take(np.zeros(5, int)), cfg).all()
    south = Facing(np.radians([195.0]), np.radians([3.0]), np.radians([10.0]), np.array([True]))
    assert not facings_compatible(west, south, 60.0, 3.0)[0]
    near = Facing(np.radians([250.0]), np.radians([3.0]), np.radians([10.0]), np.array([True]))
    assert facings_compatible(west, near, 60.0, 3.0)[0]
    assert facings_compatible(west, unknown, 60.0, 3.0)[0]
    assert angle_between(np.radians(350.0), np.radians(10.0)) == pytest.approx(np.radians(20.0))


def _rays_at(target: np.ndarray, origins: np.ndarray) -> LocalRays:
    d = target - origins
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = len(origins)
    return LocalRays(
        origins, d, *np.full((2, n), 0.01), *np.full((2, n), 1.0), np.zeros(n), np.zeros(n),
        np.arange(n), np.full(n, CLS, np.int64),
    )  # fmt: skip


def test_association_refuses_a_ray_from_the_other_street_only() -> None:
    """One landmark seen from the West (facing 285 deg); rays at it from its own street are
    associated, the same rays from the street to its South are refused with its facing and
    associated without (position alone cannot tell)."""
    x = np.array([[0.0, 0.0, 2.4]])
    cov = np.eye(3)[None] * 1.0
    cls = np.array([CLS], np.int64)
    facing = Facing(np.radians([285.0]), np.radians([2.0]), np.radians([12.0]), np.array([True]))
    cfg = GateConfig()
    from_west = _rays_at(x[0], np.array([[-30.0, 4.0, 1.5], [-20.0, 4.0, 1.5], [-8.0, 5.0, 1.5]]))
    from_south = _rays_at(x[0], np.array([[2.5, -30.0, 1.5], [2.5, -20.0, 1.5], [3.0, -12, 1.5]]))
    assert (associate(from_west, x, cov, cls, cfg, facing).landmark == 0).all()
    assert (associate(from_south, x, cov, cls, cfg).landmark == 0).all()
    assert (associate(from_south, x, cov, cls, cfg, facing).landmark == -1).all()
    # a facing not yet known constrains nothing
    unknown = Facing(*np.zeros((3, 1)), np.array([False]))
    assert (associate(from_south, x, cov, cls, cfg, unknown).landmark == 0).all()


# --- a corner: two signs of one class, 6.9 m apart, facing West and South -----------------

WEST_SIGN = np.array([-2.7, -4.1, 2.4])
"""Faces West (270): seen by eastbound cars on y = -1.75 (right of the street y = 0)."""
SOUTH_SIGN = np.array([4.1, -2.9, 2.4])
"""Faces South (180): seen by northbound cars on x = 1.75 (right of the street x = 0)."""


def corner_pass(frame, p: int, rng: np.random.Generator) -> tuple[object, np.ndarray]:
    """Pass ``p``: even passes eastbound (they see the West sign), odd northbound (the
    South sign); 12 images from 60 m to 9 m before the junction; the pass's GNSS bias
    1 m per axis, 0.01 rad on the directions. Also the true origins."""
    s = np.linspace(-60.0, -9.0, 12)
    if p % 2 == 0:
        a, sign = np.stack([s, np.full(12, -1.75), np.full(12, 1.5)], 1), WEST_SIGN
    else:
        a, sign = np.stack([np.full(12, 1.75), s, np.full(12, 1.5)], 1), SOUTH_SIGN
    meas = a + np.r_[rng.normal(0, 1.0, 2), 0.0]
    v = sign - a + rng.normal(0, 0.01, (12, 3)) * np.linalg.norm(sign - a, axis=1)[:, None]
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    lat, lon, h = frame.to_geodetic(meas)
    obs = ray_observations(lat, lon, h, d, np.arange(12), np.arange(12) + 100 * p, CLS, 0.01)
    return replace(obs, t=np.full(12, T0 + 30.0 * p)), a


def test_a_corner_pair_facing_two_streets_stays_two_landmarks(tmp_path: Path) -> None:
    """12 passes on each street, matcher then solver: two landmarks, each near its sign
    (within 2.5 m: the pass bias over 12 passes), each published facing within 3 of its
    sigmas (plus the 0.01 rad ray noise) of the true mean direction its sign was seen from,
    and within the 70-degree cone of its panel normal."""
    m = MatcherService(ServiceOptions(data_dir=tmp_path / "m"), MatcherConfig())
    m.pubs = Sink()  # type: ignore[assignment]
    s = SolverService(ServiceOptions(data_dir=tmp_path / "s"))
    s.pubs = Sink()  # type: ignore[assignment]
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    rng = np.random.default_rng(11)
    seen_from = {0: [], 1: []}
    for p in range(24):
        obs, a = corner_pass(frame, p, rng)
        sign = WEST_SIGN if p % 2 == 0 else SOUTH_SIGN
        seen_from[p % 2].append(a - sign)
        body = ObsGroup(f"veh-{p % 5}", p, p, T0 + 30.0 * p + 5.0, obs).to_bytes()
        m._apply_in_transaction([LogEntry("obs", "ingest-t", tile, p + 1, p + 1, body)])
        s._apply_in_transaction([LogEntry.from_bytes(b) for _k, b in m.pubs.sent])
        m.pubs.sent.clear()
    final = {}
    for _k, b in s.pubs.sent:
        u = updates_from_bytes(LogEntry.from_bytes(b).body)
        for k in range(len(u.landmarks)):
            final[int(u.landmarks.id[k])] = u.landmarks.take(np.array([k]))
        for i in u.removed.id.tolist():
            final.pop(int(i), None)
    assert len(m.state.landmarks) == 2 and len(final) == 2
    for sign, normal, k in ((WEST_SIGN, 270.0, 0), (SOUTH_SIGN, 180.0, 1)):
        rel = np.concatenate(seen_from[k])
        truth = float(
            np.degrees(np.arctan2(view_vectors(rel).sum(0)[0], view_vectors(rel).sum(0)[1]))
        )
        best = None
        for lm in final.values():
            e = frame.from_geodetic(lm.lat, lm.lon, lm.h)[0]
            if np.hypot(*(e - sign)[:2]) < 2.5:
                best = lm
        assert best is not None, f"no landmark at the sign facing {normal}"
        az, sigma, known = best.facing()
        assert known[0]
        bound = 3.0 * np.hypot(sigma[0], np.degrees(0.01))
        assert float(angle_between(np.radians(az[0]), np.radians(truth))) <= np.radians(bound)
        assert float(angle_between(np.radians(az[0]), np.radians(normal))) <= np.radians(70.0)
