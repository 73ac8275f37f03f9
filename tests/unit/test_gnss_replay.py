"""Real phone GNSS errors replayed into the simulator (fleetsim.gnss_replay): the traces,
a pass's draw, the course over ground, and a drive whose fixes carry them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import t as t_dist

from fleetsim.drive import DriveParams, simulate_pass
from fleetsim.evaluation.fleet_eval import PASS_S, FleetEvalConfig
from fleetsim.gnss_replay import (
    ReplayedGnss,
    course_over_ground,
    course_with_errors,
    gsdc,
    load_traces,
    velocity_error_sigma,
)
from fleetsim.noise import FLEET
from fleetsim.route import Path as RoutePath
from fleetsim.world import straight_road
from hdmap.geo.geodesy import ecef_to_enu_vectors
from vehicle.config import load_vehicle_model

MODEL = load_vehicle_model()


def test_the_two_traces_load_as_the_data_readme_describes():
    traces = load_traces()
    assert [t.name.split("/")[-1] for t in traces] == ["Pixel4", "Pixel4XLModded"]
    assert [len(t.t) for t in traces] == [1737, 1743]
    for t in traces:
        assert 1700 < t.span_s < 1800 and np.all(np.diff(t.t) > 0)
    # the README's medians of the horizontal error: 0.80 m and 1.82 m
    medians = [float(np.median(np.hypot(t.east, t.north))) for t in traces]
    assert medians == pytest.approx([0.80, 1.82], abs=0.01)


def test_a_pass_gets_one_traces_errors_at_its_times():
    g = gsdc()
    t = 1000.0 + np.arange(0.0, 60.0, 0.2)
    err = g.sample(np.random.default_rng(3), t)
    rng = np.random.default_rng(3)  # the draw: a trace, then a start second that fits
    tr = g.traces[int(rng.integers(len(g.traces)))]
    start = rng.uniform(0.0, tr.span_s - (t[-1] - t[0]))
    e, n = tr.at(start + (t - t[0]))
    np.testing.assert_allclose(err.bias_enu[:, 0], e)
    np.testing.assert_allclose(err.bias_enu[:, 1], n)
    np.testing.assert_allclose(err.velocity_enu, tr.rate_at(start + (t - t[0])))
    i = np.searchsorted(tr.t, start)  # on the recorded samples between which it falls
    assert min(tr.east[i - 1], tr.east[i]) - 1e-9 <= e[0] <= max(tr.east[i - 1], tr.east[i]) + 1e-9
    again = g.sample(np.random.default_rng(3), t)
    np.testing.assert_array_equal(again.bias_enu, err.bias_enu)
    assert not err.multipath.any() and np.all(err.heading_rad == 0.0)


def test_reported_sigmas_are_measured_on_the_data():
    g = gsdc()
    errs = np.concatenate([np.concatenate([t.east, t.north]) for t in g.traces])
    assert g.reported_sigma_h_m == pytest.approx(np.sqrt(np.mean(errs**2)))
    course = np.concatenate([t.course_errors() for t in g.traces])
    assert 1000 < course.size and g.reported_sigma_heading_deg == pytest.approx(
        np.degrees(np.sqrt(np.mean(course**2))), abs=1e-3
    )
    assert g.reported_sigma_v_m == FLEET.gnss.reported_sigmas()[1]


def test_course_over_ground_of_a_straight_track_is_its_azimuth():
    t = np.arange(10.0)
    az = np.radians(30.0)
    enu = np.column_stack([np.sin(az) * 8 * t, np.cos(az) * 8 * t])
    np.testing.assert_allclose(course_over_ground(t, enu), az)
    assert course_over_ground(t[:1], enu[:1]).tolist() == [0.0]


def test_course_with_errors_is_the_true_course_plus_what_the_error_rate_makes_of_it():
    t = np.arange(0.0, 10.0, 0.2)
    az = np.full(t.size, np.radians(30.0))
    enu = np.column_stack([np.sin(az) * 10 * t, np.cos(az) * 10 * t])
    np.testing.assert_allclose(course_with_errors(t, az, enu, np.zeros((t.size, 3))), az)
    # an error growing 1 m/s to the east of a car going north at 10 m/s: atan(1/10)
    north = np.zeros(t.size)
    track = np.column_stack([np.zeros(t.size), 10.0 * t])
    err = np.column_stack([1.0 * t, np.zeros(t.size), np.zeros(t.size)])
    np.testing.assert_allclose(course_with_errors(t, north, track, err), np.arctan(0.1))
    # or with the rate given (the replay's, per logged second)
    rate = np.column_stack([np.full(t.size, 1.0), np.zeros(t.size)])
    np.testing.assert_allclose(
        course_with_errors(t, north, track, np.zeros((t.size, 3)), rate), np.arctan(0.1)
    )


def test_a_drive_with_replayed_errors_takes_its_heading_from_the_fix_track():
    world = straight_road(5.0, 2.4)
    noise = FleetEvalConfig(out=None, gnss="gsdc").noise()  # type: ignore[arg-type]
    assert isinstance(noise.gnss, ReplayedGnss) and noise.name == "fleet+gsdc"
    path = RoutePath.along(world, [0, 1])
    fixes, _det, truth = simulate_pass(world, path, MODEL, noise, np.random.default_rng(1))
    cog = course_with_errors(
        fixes.t,
        truth.fix_heading_rad,
        truth.antenna_enu,
        truth.gnss.total_enu,
        truth.gnss.velocity_enu,
    )
    fwd = np.column_stack([np.sin(cog), np.cos(cog), np.zeros(len(cog))])
    local = ecef_to_enu_vectors(world.frame.vectors_to_ecef(fwd), fixes.lat, fixes.lon)
    want = np.degrees(np.arctan2(local[:, 0], local[:, 1])) % 360.0
    np.testing.assert_allclose(fixes.heading_deg, want, atol=1e-9)
    assert np.all(fixes.sigma_h_m == noise.gnss.reported_sigmas()[0])
    # the simulated receiver keeps its own heading model
    fleet_fixes, _, fleet_truth = simulate_pass(world, path, MODEL, FLEET, np.random.default_rng(1))
    assert not FLEET.gnss.heading_from_track
    assert fleet_truth.gnss.heading_bias_rad != 0.0
    with pytest.raises(ValueError, match="gnss 'rtk'"):
        replace(FleetEvalConfig(out=None), gnss="rtk").noise()  # type: ignore[arg-type]
    assert len(fleet_fixes.t) == len(fixes.t)


def test_the_claimed_course_sigma_is_the_velocity_error_over_the_speed():
    g = gsdc()
    assert g.velocity_sigma_mps == pytest.approx(velocity_error_sigma(g.traces))
    assert 0.1 < g.velocity_sigma_mps < 1.0
    v = np.array([8.0, 11.0, 25.0])
    np.testing.assert_allclose(
        g.heading_sigma_deg(v), np.degrees(np.arctan(g.velocity_sigma_mps / v)), atol=5e-4
    )
    tr = g.traces[0]  # the rate over the logged second that holds a time
    mid = 0.5 * (tr.t[10] + tr.t[11])
    assert tr.rate_at(np.array([mid]))[0, 0] == pytest.approx(
        (tr.east[11] - tr.east[10]) / (tr.t[11] - tr.t[10])
    )
    assert FLEET.gnss.heading_sigma_deg(v).tolist() == [FLEET.gnss.reported_sigmas()[2]] * 3


@pytest.mark.parametrize("speed", [8.0, 14.0])
def test_simulated_fixes_claim_the_course_error_they_have(speed):
    """At one speed, the course error over the claimed sigma has mean square 1: the passes
    draw independently, so each pass's mean square is one sample and 1 must lie in the
    99.9 % t interval of their mean (40 passes). The constant 1.013 deg claimed before
    (the recorded car's 25 m/s) gives about 4 at 8 m/s."""
    world = straight_road(5.0, 2.4)
    noise = FleetEvalConfig(out=None, gnss="gsdc").noise()  # type: ignore[arg-type]
    path = RoutePath.along(world, [0, 1])
    params = DriveParams(speed_mps=speed)
    rng = np.random.default_rng(7)
    per_pass = []
    for _ in range(40):
        fixes, _det, truth = simulate_pass(world, path, MODEL, noise, rng, params=params)
        err = np.angle(np.exp(1j * (np.radians(fixes.heading_deg) - truth.fix_heading_rad)))
        per_pass.append(np.mean((err / np.radians(fixes.sigma_heading_deg)) ** 2))
    m = np.asarray(per_pass)
    half = t_dist.ppf(0.9995, m.size - 1) * m.std(ddof=1) / np.sqrt(m.size)
    assert abs(m.mean() - 1.0) < half, (m.mean(), half)


def test_fleet_totals_claims_the_receivers_total_errors():
    noise = FleetEvalConfig(out=None, gnss="fleet-totals").noise()  # type: ignore[arg-type]
    g = FLEET.gnss
    assert noise.name == "fleet-totals"
    # the same errors: only the claims differ
    assert replace(noise.gnss, reported_sigma_h_m=None, reported_sigma_v_m=None,
                   reported_sigma_heading_deg=None) == g  # fmt: skip
    s_h, s_v, s_hd = noise.gnss.reported_sigmas()
    assert PASS_S == 90.0  # the figures below
    assert s_h == pytest.approx(np.sqrt(1.0 + 2.5**2 + PASS_S * 0.2**2))  # 3.29 m
    assert s_v == pytest.approx(np.sqrt(1.5**2 + 3.5**2 + PASS_S * 0.3**2))  # 4.75 m
    assert s_hd == pytest.approx(np.degrees(np.hypot(0.01, 0.02)), abs=1e-3)  # 1.28 deg
    assert FLEET.gnss.reported_sigmas() == (1.0, 1.5, 0.573)
