"""Vehicle trust (hdmap/mapping/trust.py): the offset test, probation and its one-time
settlement, and the weight of a vehicle whose rays keep failing the gate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap.mapping.trust import CAUGHT, NEW, TRUSTED, FleetOffsets, TrustConfig, VehicleTrust

CFG = TrustConfig()  # defaults: probation on (10 passes, promote below 4.61)


def vehicle(offsets, passes_per_unit: int = 1) -> VehicleTrust:
    """A vehicle with one offset per pass (exactly known: zero estimate covariance)."""
    t = VehicleTrust()
    for p, o in enumerate(offsets):
        for _ in range(passes_per_unit):
            t.add_offset(np.asarray(o, float), np.zeros((2, 2)), CFG.bias_sigma_m, pass_id=p)
    return t


def honest(rng, n):
    return vehicle(rng.normal(0.0, 2.5, (n, 2)))


def test_defaults_hold_new_vehicles_at_the_probation_weight():
    t = VehicleTrust()
    assert t.status == NEW and t.held(CFG)
    assert t.weight(CFG) == CFG.probation_weight == 0.05
    assert not t.held(replace(CFG, probation_passes=0))
    assert not t.held(replace(CFG, enabled=False))


def test_an_honest_vehicle_is_promoted_once_after_enough_passes():
    rng = np.random.default_rng(1)
    t = honest(rng, 9)
    assert t.settle(CFG) is None and t.held(CFG)  # 9 passes: not yet
    t = honest(np.random.default_rng(1), 10)
    assert t.chi2() <= CFG.promote_chi2
    assert t.settle(CFG) == TRUSTED
    assert t.weight(CFG) == 1.0 and not t.held(CFG)
    assert t.settle(CFG) is None  # settled for good
    for _ in range(5):  # later offsets away from zero weigh it down, never re-hold it
        t.add_offset(np.array([6.0, 0.0]), np.zeros((2, 2)), CFG.bias_sigma_m)
    assert t.status == TRUSTED and not t.held(CFG) and t.settle(CFG) is None


def test_units_of_one_pass_count_once():
    t = vehicle(np.random.default_rng(2).normal(0.0, 2.5, (10, 2)), passes_per_unit=3)
    assert t.passes == 10


@pytest.mark.parametrize("shift", [(5.0, 3.0), (-6.0, 0.0)])
def test_a_shifted_vehicle_is_caught_not_promoted(shift):
    offsets = np.random.default_rng(3).normal(0.0, 2.5, (14, 2)) + shift
    t = VehicleTrust()
    statuses = []
    for p, o in enumerate(offsets):  # settled after every pass, as the matcher does
        t.add_offset(o, np.zeros((2, 2)), CFG.bias_sigma_m, pass_id=p)
        statuses.append(t.settle(CFG))
    settled = [s for s in statuses if s is not None]
    assert settled == [CAUGHT]  # once, and before it could be promoted
    assert statuses.index(CAUGHT) < CFG.probation_passes
    assert t.weight(CFG) < 0.2 * CFG.probation_weight  # probation weight x the chi2 factor
    assert not t.held(CFG)


def test_offsets_are_tested_against_the_fleet_reference():
    """A map pulled by a shifted vehicle shifts every honest vehicle's offsets too."""
    rng = np.random.default_rng(4)
    pull = np.array([-1.5, -0.9])
    fleet = FleetOffsets(CFG)
    trusts = {f"v{i}": vehicle(rng.normal(0.0, 1.0, (12, 2)) + pull) for i in range(4)}
    trusts["rogue"] = vehicle(rng.normal(0.0, 1.0, (12, 2)) + pull + [5.0, 3.0])
    for v, t in trusts.items():
        fleet.update(v, t)
    ref = fleet.reference()
    np.testing.assert_allclose(ref, pull, atol=0.6)
    assert all(trusts[f"v{i}"].chi2(ref) < CFG.promote_chi2 for i in range(4))
    assert trusts["v0"].chi2() > trusts["v0"].chi2(ref)  # against zero they look shifted
    assert trusts["rogue"].suspect(CFG, ref)
    np.testing.assert_allclose(trusts["rogue"].mean_offset(ref), [5.0, 3.0], atol=0.8)


def test_a_vehicle_whose_rays_keep_failing_the_gate_weighs_less():
    cfg = replace(CFG, probation_passes=0)
    t = VehicleTrust()
    t.add_gate(offered=150, passed=10)
    assert t.weight(cfg) == 1.0  # fewer than min_gated rays offered: no verdict yet
    t.add_gate(offered=150, passed=50)
    fail = 1.0 - 60 / 300
    assert t.weight(cfg) == pytest.approx(((1.0 - fail) / (1.0 - cfg.max_gate_failure)) ** 2)
    good = VehicleTrust()
    good.add_gate(offered=300, passed=200)
    assert good.weight(cfg) == 1.0
    worst = VehicleTrust()
    worst.add_gate(offered=1000, passed=0)
    assert worst.weight(cfg) == cfg.min_weight
