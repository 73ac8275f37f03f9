"""Pinhole camera with Brown-Conrady distortion, and rigid sensor mounts.

Frames
------
- Camera (OpenCV): x right, y down, z forward along the optical axis.
- Vehicle (ISO 8855): x forward, y left, z up; origin at the vehicle reference point.
- A mount is the pose of a sensor in the vehicle frame: ``p_vehicle = R @ p_sensor + t``.

>>> cam = Intrinsics(fx=1400, fy=1400, cx=960, cy=540, width=1920, height=1080)
>>> cam.pixel_to_normalized(np.array([[1100.0, 540.0]])).tolist()
[[0.1, 0.0]]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

# Camera axes expressed in the vehicle frame for a camera looking straight ahead:
# columns are x_c (right) = -y_v, y_c (down) = -z_v, z_c (forward) = +x_v.
R_VEHICLE_CAMERA_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rot_x(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_matrix(roll: float, pitch: float, yaw: float) -> Array:
    """Z-Y-X (yaw, pitch, roll) rotation, angles in radians."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


@dataclass(frozen=True)
class Mount:
    """Pose of a sensor in the vehicle frame (translation m, rotation matrix)."""

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: Array = field(default_factory=lambda: np.eye(3))

    @classmethod
    def from_rpy_deg(
        cls, translation: ArrayLike, rpy_deg: ArrayLike = (0.0, 0.0, 0.0), base: Array | None = None
    ) -> Mount:
        roll, pitch, yaw = np.radians(np.asarray(rpy_deg, float))
        r = rpy_matrix(roll, pitch, yaw)
        if base is not None:
            r = r @ base
        t = tuple(float(v) for v in np.asarray(translation, float))
        return cls(translation=t, rotation=r)  # type: ignore[arg-type]

    @property
    def t(self) -> Array:
        return np.asarray(self.translation, float)

    def matrix(self) -> Array:
        """Homogeneous 4x4 transform sensor -> vehicle (the paper's T_V^S inverse)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.t
        return m


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics K and Brown-Conrady distortion (k1, k2, p1, p2, k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(c) > 0.0 for c in self.dist)

    def distort(self, xy: ArrayLike) -> Array:
        """Ideal normalised coordinates -> distorted normalised coordinates."""
        p = np.asarray(xy, float)
        k1, k2, p1, p2, k3 = self.dist
        x, y = p[..., 0], p[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort(self, xy_d: ArrayLike, iterations: int = 20) -> Array:
        """Invert :meth:`distort` by fixed-point iteration (converges for mild lenses)."""
        pd = np.asarray(xy_d, float)
        if not self.has_distortion:
            return pd.copy()
        k1, k2, p1, p2, k3 = self.dist
        x, y = pd[..., 0].copy(), pd[..., 1].copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            x = (pd[..., 0] - dx) / radial
            y = (pd[..., 1] - dy) / radial
        return np.stack([x, y], axis=-1)

    def pixel_to_normalized(self, uv: ArrayLike) -> Array:
        """Pixels (..., 2) -> ideal normalised image coordinates (x/z, y/z)."""
        p = np.asarray(uv, float)
        xd = np.stack([(p[..., 0] - self.cx) / self.fx, (p[..., 1] - self.cy) / self.fy], axis=-1)
        return self.undistort(xd)

    def normalized_to_pixel(self, xy: ArrayLike) -> Array:
        d = self.distort(xy)
        return np.stack([d[..., 0] * self.fx + self.cx, d[..., 1] * self.fy + self.cy], axis=-1)

    def project(self, p_cam: ArrayLike) -> tuple[Array, NDArray[np.bool_]]:
        """Camera-frame points (..., 3) -> pixels (..., 2) and an in-front mask."""
        p = np.asarray(p_cam, float)
        z = p[..., 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        xy = np.stack([p[..., 0] / zs, p[..., 1] / zs], axis=-1)
        return self.normalized_to_pixel(xy), front

    def in_image(self, uv: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        p = np.asarray(uv, float)
        return (
            (p[..., 0] >= margin)
            & (p[..., 0] <= self.width - 1 - margin)
            & (p[..., 1] >= margin)
            & (p[..., 1] <= self.height - 1 - margin)
        )
