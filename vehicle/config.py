"""Vehicle + camera configuration: a TOML file -> :class:`vehicle.geoloc.VehicleModel`.

The format is documented in ``vehicle/default_vehicle.toml`` (shipped with the
package, loaded when no file is given). Every error names the offending key:

>>> parse_vehicle_config({"camera": {"fx": 1.0}})
Traceback (most recent call last):
...
vehicle.config.VehicleConfigError: camera.fy: missing
>>> cfg = load_vehicle_config()
>>> cfg.fx, cfg.camera_xyz, cfg.gnss_xyz
(1400.0, (1.5, 0.0, 1.4), (0.0, 0.0, 1.5))
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from hdmap.geo.camera import Intrinsics
from hdmap.geo.signs import CATALOG, SignCatalog, SignCatalogError, UnknownSignClass
from vehicle.geoloc import VehicleModel

DEFAULT_FILE = "default_vehicle.toml"

Vec3 = tuple[float, float, float]


class VehicleConfigError(ValueError):
    """A bad vehicle configuration; the message starts with the key (``camera.fx: ...``)."""


@dataclass(frozen=True)
class VehicleConfig:
    """A parsed, validated vehicle configuration."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    """k1, k2, p1, p2, k3."""
    camera_xyz: Vec3 = (1.5, 0.0, 1.4)
    camera_rpy_deg: Vec3 = (0.0, 0.0, 0.0)
    gnss_xyz: Vec3 = (0.0, 0.0, 1.5)
    pixel_sigma: float = 3.0
    pitch_sigma_deg: float = 0.5
    min_box_px: float = 12.0
    sign_heights_m: tuple[tuple[str, float], ...] = ()
    """Per-class panel height overrides, (class name, metres)."""
    sign_catalog_file: str = ""
    """The sign catalogue file ``[signs] catalog`` names, resolved ("": the defaults)."""
    sign_catalog: SignCatalog = field(default=CATALOG, compare=False, repr=False)
    """The classes of that file (or :data:`hdmap.geo.signs.CATALOG`), before the
    ``sign_heights_m`` overrides."""
    source: str = "<dict>"

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics(
            fx=self.fx,
            fy=self.fy,
            cx=self.cx,
            cy=self.cy,
            width=self.width,
            height=self.height,
            dist=self.distortion,
        )

    def catalog(self, base: SignCatalog | None = None) -> SignCatalog:
        """``base`` (default: :attr:`sign_catalog`) with this vehicle's panel heights."""
        base = self.sign_catalog if base is None else base
        return base.with_sizes(dict(self.sign_heights_m)) if self.sign_heights_m else base

    def to_model(self, base_catalog: SignCatalog | None = None) -> VehicleModel:
        return VehicleModel.forward_camera(
            self.intrinsics,
            camera_xyz=self.camera_xyz,
            camera_rpy_deg=self.camera_rpy_deg,
            gnss_xyz=self.gnss_xyz,
            pixel_sigma=self.pixel_sigma,
            pitch_sigma_rad=math.radians(self.pitch_sigma_deg),
            min_box_px=self.min_box_px,
            catalog=self.catalog(base_catalog),
        )


# --- checked getters -----------------------------------------------------------------


def _table(m: Mapping[str, Any], key: str, path: str, required: bool = True) -> Mapping:
    full = f"{path}.{key}" if path else key
    if key not in m:
        if required:
            raise VehicleConfigError(f"{full}: missing")
        return {}
    v = m[key]
    if not isinstance(v, Mapping):
        raise VehicleConfigError(f"{full}: expected a table, got {type(v).__name__}")
    return v


def _number(
    m: Mapping[str, Any],
    key: str,
    path: str,
    default: float | None = None,
    lo: float | None = None,
    lo_open: bool = False,
) -> float:
    full = f"{path}.{key}"
    if key not in m:
        if default is None:
            raise VehicleConfigError(f"{full}: missing")
        return default
    v = m[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise VehicleConfigError(f"{full}: expected a number, got {type(v).__name__} {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise VehicleConfigError(f"{full}: must be finite, got {v}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise VehicleConfigError(f"{full}: must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    return v


def _integer(m: Mapping[str, Any], key: str, path: str, lo: int = 1) -> int:
    full = f"{path}.{key}"
    if key not in m:
        raise VehicleConfigError(f"{full}: missing")
    v = m[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise VehicleConfigError(f"{full}: expected an integer, got {type(v).__name__} {v!r}")
    if v < lo:
        raise VehicleConfigError(f"{full}: must be >= {lo}, got {v}")
    return int(v)


def _vec3(m: Mapping[str, Any], key: str, path: str, default: Vec3 | None = None) -> Vec3:
    full = f"{path}.{key}"
    if key not in m:
        if default is None:
            raise VehicleConfigError(f"{full}: missing")
        return default
    v = m[key]
    if not isinstance(v, list) or len(v) != 3:
        raise VehicleConfigError(f"{full}: expected a list of 3 numbers, got {v!r}")
    for i, x in enumerate(v):
        if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
            raise VehicleConfigError(f"{full}[{i}]: expected a finite number, got {x!r}")
    return (float(v[0]), float(v[1]), float(v[2]))


def _no_unknown(m: Mapping[str, Any], allowed: set[str], path: str) -> None:
    for k in m:
        if k not in allowed:
            full = f"{path}.{k}" if path else k
            raise VehicleConfigError(f"{full}: unknown key (allowed: {', '.join(sorted(allowed))})")


# --- parsing --------------------------------------------------------------------------


def parse_vehicle_config(
    doc: Mapping[str, Any], source: str = "<dict>", base_dir: Path | None = None
) -> VehicleConfig:
    """Validate a decoded TOML document; raises :class:`VehicleConfigError` naming the key.
    A relative ``[signs] catalog`` path is read from ``base_dir`` (the directory of the
    vehicle file; None: the working directory)."""
    _no_unknown(doc, {"camera", "gnss", "noise", "signs"}, "")
    cam = _table(doc, "camera", "")
    _no_unknown(cam, {"width", "height", "fx", "fy", "cx", "cy", "distortion", "mount"}, "camera")
    fx = _number(cam, "fx", "camera", lo=0.0, lo_open=True)
    fy = _number(cam, "fy", "camera", lo=0.0, lo_open=True)
    width = _integer(cam, "width", "camera")
    height = _integer(cam, "height", "camera")
    cx = _number(cam, "cx", "camera")
    cy = _number(cam, "cy", "camera")
    if not 0.0 <= cx <= width:
        raise VehicleConfigError(f"camera.cx: must lie in [0, width={width}], got {cx:g}")
    if not 0.0 <= cy <= height:
        raise VehicleConfigError(f"camera.cy: must lie in [0, height={height}], got {cy:g}")

    dist_t = _table(cam, "distortion", "camera", required=False)
    names = ("k1", "k2", "p1", "p2", "k3")
    _no_unknown(dist_t, set(names), "camera.distortion")
    dist = tuple(_number(dist_t, k, "camera.distortion", default=0.0) for k in names)

    mount = _table(cam, "mount", "camera")
    _no_unknown(mount, {"xyz", "rpy_deg"}, "camera.mount")
    cam_xyz = _vec3(mount, "xyz", "camera.mount")
    cam_rpy = _vec3(mount, "rpy_deg", "camera.mount", default=(0.0, 0.0, 0.0))

    gnss = _table(doc, "gnss", "")
    _no_unknown(gnss, {"mount"}, "gnss")
    gmount = _table(gnss, "mount", "gnss")
    _no_unknown(gmount, {"xyz"}, "gnss.mount")
    gnss_xyz = _vec3(gmount, "xyz", "gnss.mount")

    noise = _table(doc, "noise", "", required=False)
    _no_unknown(noise, {"pixel_sigma", "pitch_sigma_deg", "min_box_px"}, "noise")
    pixel_sigma = _number(noise, "pixel_sigma", "noise", default=3.0, lo=0.0, lo_open=True)
    pitch_sigma = _number(noise, "pitch_sigma_deg", "noise", default=0.5, lo=0.0)
    min_box = _number(noise, "min_box_px", "noise", default=12.0, lo=1.0)

    signs = _table(doc, "signs", "", required=False)
    _no_unknown(signs, {"catalog", "heights_m"}, "signs")
    catalog_file, catalog = _sign_catalog(signs, base_dir)
    heights = _table(signs, "heights_m", "signs", required=False)
    overrides = []
    for ref in heights:
        try:
            name = catalog.by_ref(ref).name
        except UnknownSignClass as e:
            raise VehicleConfigError(f"signs.heights_m.{ref}: {e}") from None
        overrides.append((name, _number(heights, ref, "signs.heights_m", lo=0.0, lo_open=True)))

    return VehicleConfig(
        width=width,
        height=height,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        distortion=dist,  # type: ignore[arg-type]
        camera_xyz=cam_xyz,
        camera_rpy_deg=cam_rpy,
        gnss_xyz=gnss_xyz,
        pixel_sigma=pixel_sigma,
        pitch_sigma_deg=pitch_sigma,
        min_box_px=min_box,
        sign_heights_m=tuple(sorted(overrides)),
        sign_catalog_file=catalog_file,
        sign_catalog=catalog,
        source=source,
    )


def _sign_catalog(signs: Mapping[str, Any], base_dir: Path | None) -> tuple[str, SignCatalog]:
    """(resolved path, catalogue) of ``[signs] catalog`` (format: ``deploy/signs.toml``)."""
    if "catalog" not in signs:
        return "", CATALOG
    v = signs["catalog"]
    if not isinstance(v, str) or not v:
        raise VehicleConfigError(f"signs.catalog: expected a file path, got {v!r}")
    path = Path(v)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    try:
        return str(path), SignCatalog.from_toml(path)
    except SignCatalogError as e:
        raise VehicleConfigError(f"signs.catalog: {e}") from None


def default_config_text() -> str:
    return resources.files("vehicle").joinpath(DEFAULT_FILE).read_text(encoding="utf-8")


def load_vehicle_config(path: str | Path | None = None) -> VehicleConfig:
    """Load and validate a vehicle TOML file (None: the packaged default)."""
    base_dir = None if path is None else Path(path).parent
    if path is None:
        text, source = default_config_text(), f"vehicle/{DEFAULT_FILE}"
    else:
        try:
            text, source = Path(path).read_text(encoding="utf-8"), str(path)
        except OSError as e:
            raise VehicleConfigError(f"{path}: cannot read ({e.strerror or e})") from e
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise VehicleConfigError(f"{source}: not valid TOML: {e}") from e
    try:
        return parse_vehicle_config(doc, source, base_dir)
    except VehicleConfigError as e:
        raise VehicleConfigError(f"{e} (in {source})") from None


def load_vehicle_model(path: str | Path | None = None) -> VehicleModel:
    """:func:`load_vehicle_config` then :meth:`VehicleConfig.to_model`."""
    return load_vehicle_config(path).to_model()


__all__ = [
    "VehicleConfig",
    "VehicleConfigError",
    "load_vehicle_config",
    "load_vehicle_model",
    "parse_vehicle_config",
]
