"""``hdmap calibrate-map``: reading surveyed signs and measuring the floor from a map.

The map is synthetic: landmarks around Helsinki whose errors are drawn from their
published covariance (0.1-0.5 m, published with the solver's 0.1 m floor) plus a true
floor of 0.3 m per axis; some controls must not pair (another class, too few passes).
"""

from __future__ import annotations

import argparse
from types import SimpleNamespace

import numpy as np
import pytest

from hdmap.cli.calibrate_map import floor_from_map, published_floor, read_controls
from hdmap.geo.geodesy import EnuFrame
from services.solver.service import SolverConfig


def _map(rng, n: int = 150, floor: float = 0.3, base: float = 0.1):
    frame = EnuFrame(60.17, 24.94, 20.0)
    truth = np.column_stack([rng.uniform(-400, 400, (n, 2)), rng.uniform(1.5, 3.0, n)])
    truth[:, 0] = np.round(truth[:, 0] / 20.0) * 20.0 + np.arange(n) % 7  # > 5 m apart
    sd = rng.uniform(0.1, 0.5, (n, 3))
    cov = sd[:, :, None] ** 2 * np.eye(3)
    err = rng.normal(size=(n, 3)) * np.sqrt(sd**2 + floor**2)
    lat, lon, h = frame.to_geodetic(truth + err)
    pub = cov + base**2 * np.eye(3)
    lms = SimpleNamespace(
        lat=lat,
        lon=lon,
        h=h,
        sign_class=np.full(n, 2, np.uint16),
        n_passes=np.where(np.arange(n) < n - 5, 300, 20).astype(np.uint32),
        cov=np.column_stack(
            [pub[:, 0, 0], pub[:, 0, 1], pub[:, 0, 2], pub[:, 1, 1], pub[:, 1, 2], pub[:, 2, 2]]
        ),
    )
    c_lat, c_lon, c_h = frame.to_geodetic(truth)
    ctl = np.column_stack([c_lat, c_lon, c_h])
    cls = np.full(n, 2, np.int64)
    cls[:3] = 1  # surveyed as another class: no pair
    return lms, ctl, cls


def test_the_floor_of_a_map_is_measured_from_its_controls():
    lms, ctl, cls = _map(np.random.default_rng(0))
    args = argparse.Namespace(match_m=5.0, min_passes=150)
    art = floor_from_map(lms, ctl, cls, args, SolverConfig())
    assert art["paired"] == 150 - 3 - 5
    h = art["horizontal"]
    assert h["interval"][0] <= 0.3 <= h["interval"][1], h
    assert h["inside_after"] >= 0.95 > h["inside_before"]
    assert art["systematic_sigma_m"][0] == h["sigma_m"]
    k = art["pass_correlation"]
    assert k["kappa"] > 0 and k["inside_after"] >= 0.95 and k["controls"] == art["paired"]


def test_too_few_controls_is_an_error():
    lms, ctl, cls = _map(np.random.default_rng(1), n=25)
    with pytest.raises(ValueError, match="at least 20"):
        floor_from_map(
            lms, ctl, cls, argparse.Namespace(match_m=5.0, min_passes=150), SolverConfig()
        )


def test_control_files_are_read_and_bad_rows_named(tmp_path):
    good = tmp_path / "c.csv"
    good.write_text("traffic_sign,lat,lon,h\nFI:231,60.17,24.94,21.5\ngive_way,60.18,24.95,22\n")
    xyz, cls = read_controls(good)
    assert xyz.shape == (2, 3) and cls.tolist() == [2, 2]
    cases = {
        "traffic_sign,lat,lon\nFI:231,60,24\n": "missing column",
        "traffic_sign,lat,lon,h\nXX:999,60,24,1\n": r"c.csv:2: traffic_sign",
        "traffic_sign,lat,lon,h\nFI:231,north,24,1\n": r"c.csv:2: lat/lon/h",
        "traffic_sign,lat,lon,h\nFI:231,95,24,1\n": "out of range",
        "traffic_sign,lat,lon,h\n": "no rows",
    }
    for text, message in cases.items():
        good.write_text(text)
        with pytest.raises(ValueError, match=message):
            read_controls(good)


def test_the_published_floor_comes_from_the_services_config(tmp_path):
    cfg = tmp_path / "services.toml"
    cfg.write_text("[solver]\nsystematic_sigma_m = [0.25, 0.25, 0.4]\npass_correlation = 0.003\n")
    assert published_floor(str(cfg)).systematic_sigma_m == (0.25, 0.25, 0.4)
    assert published_floor(str(cfg)).pass_correlation == 0.003
    assert published_floor(None).systematic_sigma_m == (0.1, 0.1, 0.1)
