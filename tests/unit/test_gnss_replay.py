"""Real phone GNSS errors replayed into the simulator (fleetsim.gnss_replay): the traces,
a pass's draw, the course over ground, and a drive whose fixes carry them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fleetsim.drive import simulate_pass
from fleetsim.evaluation.fleet_eval import FleetEvalConfig
from fleetsim.gnss_replay import (
    ReplayedGnss,
    course_over_ground,
    course_with_errors,
    gsdc,
    load_traces,
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


def test_a_drive_with_replayed_errors_takes_its_heading_from_the_fix_track():
    world = straight_road(5.0, 2.4)
    noise = FleetEvalConfig(out=None, gnss="gsdc").noise()  # type: ignore[arg-type]
    assert isinstance(noise.gnss, ReplayedGnss) and noise.name == "fleet+gsdc"
    path = RoutePath.along(world, [0, 1])
    fixes, _det, truth = simulate_pass(world, path, MODEL, noise, np.random.default_rng(1))
    cog = course_with_errors(
        fixes.t, truth.fix_heading_rad, truth.antenna_enu, truth.gnss.total_enu
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
