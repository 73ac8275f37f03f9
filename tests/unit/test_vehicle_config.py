"""vehicle.config: TOML -> VehicleModel, and errors that name the key."""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from hdmap.geo.camera import R_VEHICLE_CAMERA_FORWARD
from hdmap.geo.signs import CATALOG
from vehicle.config import (
    VehicleConfig,
    VehicleConfigError,
    default_config_text,
    load_vehicle_config,
    load_vehicle_model,
    parse_vehicle_config,
)

DEFAULT_TEXT = default_config_text()
DEFAULT_DOC = tomllib.loads(DEFAULT_TEXT)


def test_default_file_ships_with_the_package() -> None:
    import vehicle

    assert (Path(vehicle.__file__).parent / "default_vehicle.toml").is_file()


def test_default_model_matches_the_documented_defaults() -> None:
    cfg = load_vehicle_config()
    assert isinstance(cfg, VehicleConfig)
    m = load_vehicle_model()
    i = m.intrinsics
    assert (i.width, i.height, i.fx, i.fy, i.cx, i.cy) == (1920, 1080, 1400.0, 1400.0, 960.0, 540.0)
    assert i.dist == (0.0, 0.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(m.camera_mount.t, [1.5, 0.0, 1.4])
    np.testing.assert_allclose(m.camera_mount.rotation, R_VEHICLE_CAMERA_FORWARD, atol=1e-15)
    np.testing.assert_allclose(m.gnss_mount.t, [0.0, 0.0, 1.5])
    assert m.pixel_sigma == 3.0
    assert m.pitch_sigma_rad == pytest.approx(math.radians(0.5))
    assert m.min_box_px == 12.0
    assert m.catalog is CATALOG


def test_load_from_a_file_with_every_option(tmp_path: Path) -> None:
    text = (
        DEFAULT_TEXT.replace("k1 = 0.0", "k1 = -0.12")
        .replace("p2 = 0.0", "p2 = 0.001")
        .replace("rpy_deg = [0.0, 0.0, 0.0]", "rpy_deg = [0.0, 5.0, 0.0]")
        .replace("pixel_sigma = 3.0", "pixel_sigma = 2")
        .replace("# [signs.heights_m]\n# speed_limit_30 = 0.9", "[signs.heights_m]\nstop = 0.9")
    )
    f = tmp_path / "car.toml"
    f.write_text(text)
    cfg = load_vehicle_config(f)
    assert cfg.distortion == (-0.12, 0.0, 0.0, 0.001, 0.0)
    assert cfg.pixel_sigma == 2.0
    assert cfg.sign_heights_m == (("stop", 0.9),)
    m = cfg.to_model()
    assert m.intrinsics.has_distortion
    assert m.catalog.by_name("stop").height_m == 0.9
    assert m.catalog.by_name("give_way").height_m == CATALOG.by_name("give_way").height_m
    # Positive pitch turns the optical axis (camera z) downward in the vehicle frame.
    z_axis = m.camera_mount.rotation[:, 2]
    assert z_axis[2] == pytest.approx(-math.sin(math.radians(5.0)))
    assert cfg.source == str(f)


def test_optional_sections_may_be_omitted() -> None:
    doc = copy.deepcopy(DEFAULT_DOC)
    del doc["noise"]
    del doc["camera"]["distortion"]
    del doc["camera"]["mount"]["rpy_deg"]
    cfg = parse_vehicle_config(doc)
    assert (cfg.pixel_sigma, cfg.pitch_sigma_deg, cfg.min_box_px) == (3.0, 0.5, 12.0)
    assert cfg.camera_rpy_deg == (0.0, 0.0, 0.0)


def _set(doc: dict, dotted: str, value) -> dict:
    d = copy.deepcopy(doc)
    *parents, last = dotted.split(".")
    node = d
    for p in parents:
        node = node.setdefault(p, {})
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value
    return d


_DELETE = object()


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("camera.fx", _DELETE, "camera.fx: missing"),
        ("camera.fy", -1400.0, "camera.fy: must be > 0"),
        ("camera.fx", 0, "camera.fx: must be > 0"),
        ("camera.fx", "1400", "camera.fx: expected a number"),
        ("camera.fx", math.nan, "camera.fx: must be finite"),
        ("camera.width", "1920", "camera.width: expected an integer"),
        ("camera.width", 1920.0, "camera.width: expected an integer"),
        ("camera.height", 0, "camera.height: must be >= 1"),
        ("camera.cx", 5000.0, "camera.cx: must lie in [0, width=1920]"),
        ("camera.distortion.k1", True, "camera.distortion.k1: expected a number"),
        ("camera.distortion.k4", 0.1, "camera.distortion.k4: unknown key"),
        ("camera.mount.xyz", [1.5, 0.0], "camera.mount.xyz: expected a list of 3 numbers"),
        ("camera.mount.xyz", [1.5, "a", 1.4], "camera.mount.xyz[1]: expected a finite number"),
        ("camera.mount", _DELETE, "camera.mount: missing"),
        ("camera.mount", 3, "camera.mount: expected a table"),
        ("gnss.mount.xyz", _DELETE, "gnss.mount.xyz: missing"),
        ("gnss", _DELETE, "gnss: missing"),
        ("noise.pixel_sigma", -1.0, "noise.pixel_sigma: must be > 0"),
        ("noise.pitch_sigma_deg", -0.1, "noise.pitch_sigma_deg: must be >= 0"),
        ("noise.min_box_px", 0.5, "noise.min_box_px: must be >= 1"),
        ("noise.pixel_sigmaa", 1.0, "noise.pixel_sigmaa: unknown key"),
        ("signs.heights_m.stopp", 0.9, "signs.heights_m.stopp: unknown sign class"),
        ("signs.heights_m.stop", -0.9, "signs.heights_m.stop: must be > 0"),
        ("signs.sizes", {}, "signs.sizes: unknown key"),
        ("cameras", {}, "cameras: unknown key"),
    ],
)
def test_errors_name_the_key(key: str, value, message: str) -> None:
    with pytest.raises(VehicleConfigError) as e:
        parse_vehicle_config(_set(DEFAULT_DOC, key, value))
    assert str(e.value).startswith(message), str(e.value)


def test_file_errors_name_the_key_and_the_file(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(DEFAULT_TEXT.replace("fx = 1400.0", "fx = -1400.0"))
    with pytest.raises(VehicleConfigError, match=r"^camera\.fx: must be > 0.*bad\.toml"):
        load_vehicle_config(f)


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(VehicleConfigError, match="cannot read"):
        load_vehicle_config(tmp_path / "missing.toml")
    f = tmp_path / "broken.toml"
    f.write_text("[camera\nfx = 1")
    with pytest.raises(VehicleConfigError, match="not valid TOML"):
        load_vehicle_config(f)
    # It is a ValueError, so callers may treat it as bad input.
    assert issubclass(VehicleConfigError, ValueError)


def test_the_vehicle_reads_the_deployment_catalogue_next_to_its_file(tmp_path: Path) -> None:
    (tmp_path / "signs.toml").write_text(
        '[[class]]\ncode = 1000\nname = "de_priority_road"\nosm = "DE:306"\nheight_m = 0.6\n'
    )
    f = tmp_path / "car.toml"
    f.write_text(
        DEFAULT_TEXT + '\n[signs]\ncatalog = "signs.toml"\n'
        '[signs.heights_m]\n"DE:306" = 0.7\n"FI:231" = 0.8\n'
    )
    cfg = load_vehicle_config(f)
    assert cfg.sign_catalog_file == str(tmp_path / "signs.toml")
    assert cfg.sign_heights_m == (("de_priority_road", 0.7), ("give_way", 0.8))
    m = cfg.to_model()
    assert m.catalog.by_code(1000).height_m == 0.7 and m.catalog.code_of("DE:306") == 1000
    assert m.catalog.by_name("give_way").height_m == 0.8
    assert m.catalog.by_name("stop").height_m == CATALOG.by_name("stop").height_m
    assert 1000 not in CATALOG


@pytest.mark.parametrize(
    ("signs", "message"),
    [
        ('catalog = "missing.toml"', r"^signs\.catalog: .*missing\.toml: cannot read"),
        (
            'catalog = "bad.toml"',
            r"^signs\.catalog: .*bad\.toml: class\[0\]\.height_m: must be > 0",
        ),
        ("catalog = 3", r"^signs\.catalog: expected a file path"),
        ('catalog = "bad.toml"\nfoo = 1', r"^signs\.foo: unknown key"),
    ],
)
def test_catalogue_errors_name_the_key(tmp_path: Path, signs: str, message: str) -> None:
    (tmp_path / "bad.toml").write_text(
        '[[class]]\ncode = 1000\nname = "x"\nosm = "X:1"\nheight_m = 0.0\n'
    )
    f = tmp_path / "car.toml"
    f.write_text(DEFAULT_TEXT + f"\n[signs]\n{signs}\n")
    with pytest.raises(VehicleConfigError, match=message):
        load_vehicle_config(f)
