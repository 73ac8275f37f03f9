"""The white pitch measured from a pass's tracks (vehicle/pitch.py), against synthetic
tracks with known pitch and pixel noise.

Bounds: the MAD scale of ``n`` normal values has relative standard error
``sqrt(1.36 / n)`` (efficiency 0.37 against the standard deviation's ``1 / (2n)``);
consecutive chord residuals share rays, so only every third is independent and ``n`` is
taken as a third of the residuals. Errors are checked within ``Z = 3.89`` such standard
errors (two-sided 1e-4), propagated to the pitch std through ``s^2 = sigma^2 - p^2``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.noise import EXACT
from fleetsim.osm_town import helsinki_town
from fleetsim.pipeline import model_for
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model
from vehicle.pitch import chord_residuals, elevation, measured_sigma_el, white_pitch_sigma

Z = 3.89
CAP = np.radians(0.5)


def tracks(rng, n_tracks, pitch, pixel, rate_hz=15.0, rays=40, h=1.5, far=40.0, speed=10.0):
    """Approaches at ``speed`` toward a sign ``h`` above the camera, from ``far`` metres,
    ``rays`` frames each; elevation = truth + pitch + pixel noise (white)."""
    t1 = np.arange(rays) / rate_hz
    t = np.concatenate([t1 + 100.0 * k for k in range(n_tracks)])
    track = np.repeat(np.arange(1, n_tracks + 1), rays)
    rho = far - speed * np.tile(t1, n_tracks)
    el = np.arctan2(h, rho) + rng.normal(0.0, 1.0, t.size) * np.hypot(pitch, pixel)
    return t, el, track, np.full(t.size, pixel), rho


def bound(pitch: float, pixel: float, n_resid: int) -> float:
    """Z standard errors of the pitch estimate (module docstring)."""
    total2 = pitch**2 + pixel**2
    rel = np.sqrt(1.36 / (n_resid / 3))
    return float(Z * 2.0 * total2 * rel / (2.0 * max(pitch, 1e-12)))


def test_recovers_a_white_pitch():
    rng = np.random.default_rng(0)
    t, el, tr, pix, rho = tracks(rng, 40, pitch=0.006, pixel=0.003)
    z, _ = chord_residuals(t, el, tr, pix**2, np.ones(t.size, bool))
    assert z.size == 40 * 38  # triples never span two tracks
    s = white_pitch_sigma(t, el, tr, pix, rho, cap_rad=0.05)
    assert abs(s - 0.006) < bound(0.006, 0.003, z.size)


def test_no_pitch_gives_about_none():
    rng = np.random.default_rng(1)
    t, el, tr, pix, rho = tracks(rng, 40, pitch=0.0, pixel=0.003)
    s = white_pitch_sigma(t, el, tr, pix, rho, cap_rad=CAP)
    n = 40 * 38
    # s^2 = sigma^2 - p^2 with sigma^2 within Z * 2 * rel of p^2 (sigma^2's relative error)
    assert s <= 0.003 * np.sqrt(Z * 2.0 * np.sqrt(1.36 / (n / 3)))
    assert s < CAP / 2


def test_close_and_untracked_rays_are_left_out():
    rng = np.random.default_rng(2)
    t, el, tr, pix, rho = tracks(rng, 30, pitch=0.0, pixel=0.003)
    base = white_pitch_sigma(t, el, tr, pix, rho, cap_rad=CAP)
    # the same passes driven on to 1 m from the sign: the elevation curves sharply there
    t2, el2, tr2, pix2, rho2 = tracks(rng, 30, pitch=0.0, pixel=0.003, rays=59, far=40.0)
    assert rho2.min() < 1.5
    near = white_pitch_sigma(t2, el2, tr2, pix2, rho2, cap_rad=CAP)
    no_range = white_pitch_sigma(t2, el2, tr2, pix2, np.zeros_like(rho2), cap_rad=CAP)
    assert near < 0.003 and base < 0.003
    assert no_range > near  # the curvature is what the range filter keeps out
    untracked = white_pitch_sigma(t, el, np.zeros_like(tr), pix, rho, cap_rad=CAP)
    assert untracked == CAP  # nothing to measure: the model's bound


def test_few_triples_or_a_large_pitch_give_the_bound():
    rng = np.random.default_rng(3)
    t, el, tr, pix, rho = tracks(rng, 2, pitch=0.0, pixel=0.003, rays=10)
    assert white_pitch_sigma(t, el, tr, pix, rho, cap_rad=CAP) == CAP
    t, el, tr, pix, rho = tracks(rng, 40, pitch=0.03, pixel=0.003)
    assert white_pitch_sigma(t, el, tr, pix, rho, cap_rad=CAP) == CAP


def test_measured_sigma_el_replaces_only_the_pitch_part():
    rng = np.random.default_rng(4)
    t, el, tr, pix, rho = tracks(rng, 40, pitch=0.0, pixel=0.003)
    d = np.column_stack([np.zeros(t.size), np.cos(el), np.sin(el)])
    claimed = np.hypot(pix, CAP)
    sigma, pitch = measured_sigma_el(t, d, claimed, rho, tr, CAP)
    assert pitch < 0.003
    np.testing.assert_allclose(sigma, np.hypot(pix, pitch))
    assert np.all(sigma < claimed)


def test_agent_reports_the_pitch_its_tracks_show(tmp_path):
    """Simulated passes with exact GNSS and 3 px boxes (the simulator has no pitch error):
    the rays' elevation error is the pixel noise alone, about 0.002 rad, against the
    model's 0.5 deg bound (0.0087 rad). The claimed elevation sigma must come within 25 %
    of the true error's RMS (the chord model's curvature and the per-pass MAD's upward
    bias at about a hundred residuals; the RMS itself, over thousands of rays, errs by
    about 1 %) and stay far under the bound."""
    noise = replace(EXACT, detector=replace(EXACT.detector, pixel_sigma=3.0))
    world = helsinki_town()
    model = model_for(noise, load_vehicle_model())
    cfg = FleetConfig(n_vehicles=5, start_time=1.0e9, route_length_m=(600.0, 1200.0))
    agent = VehicleAgent("veh-p", model, tmp_path)
    err, claim = [], []
    for k, p in enumerate(Fleet(world, model, noise, cfg, seed=5).passes(8)):
        obs = agent.record(k, p.fixes, p.detections)
        sid = p.truth.sign_id[agent.last_kept]
        r = world.signs.index_of(sid)
        ok = (sid >= 0) & (r >= 0)
        origin = world.frame.from_geodetic(obs.lat, obs.lon, obs.h)[ok]
        el_true = elevation(world.signs.position[r[ok]] - origin)
        err.append(elevation(np.asarray(obs.direction)[ok]) - el_true)
        claim.append(np.asarray(obs.sigma_el)[ok])
        assert agent.last_pitch_sigma_rad < model.pitch_sigma_rad
    agent.close()
    e, c = np.concatenate(err), np.concatenate(claim)
    assert e.size > 2000
    rms_e, rms_c = np.sqrt(np.mean(e**2)), np.sqrt(np.mean(c**2))
    assert 0.8 < rms_c / rms_e < 1.25
    assert rms_c < 0.5 * model.pitch_sigma_rad
