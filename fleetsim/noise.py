"""Noise models of the simulated sensors: the GNSS receiver and the sign detector.

Two presets:

``PAPER`` -- the paper's 2D simulation (Sec. IV-A): white noise only, 5.0 m per
horizontal axis on the position, 0.35 rad on the heading, 5 px on the detection.
Every visible sign is detected, no false positives, no vertical noise (the paper
works on the North-East plane). The fix claims sigma_h 5.0 m, sigma_heading
20.05 deg (0.35 rad) and sigma_v 1.0 m: a zero vertical sigma is not a valid
observation on the wire, and 1 m is a harmless, conservative claim.

``FLEET`` -- a consumer receiver in town:

- per pass, a position bias of 2.5 m std per horizontal axis, drifting as a random
  walk of 0.2 m per sqrt(s), plus 1.0 m white noise per axis and fix;
- vertical: a per-pass bias of 3.5 m std drifting at 0.3 m per sqrt(s), plus 1.5 m
  white. Single-frequency receivers are about 1.5x worse vertically than
  horizontally; this keeps that ratio;
- heading (course over ground): a per-pass bias of 0.02 rad plus 0.01 rad white;
- multipath: 3% of the fixes are displaced by 20-50 m in a random horizontal
  direction (heading untouched: it comes from Doppler, not from positions);
- detector: 3 px std on the box centre (box size kept), detection probability
  0.8 per visible sign and image, a false positive (random class, random
  plausible box) in 2% of the images.

The fix reports what a receiver would claim: it knows its white noise, not the
per-pass bias nor multipath. By default each preset reports its white levels
(``FLEET``: sigma_h 1.0 m, sigma_v 1.5 m, sigma_heading 0.573 deg); every
reported sigma can be overridden (``GnssNoise.reported_*``).

>>> FLEET.gnss.reported_sigmas()
(1.0, 1.5, 0.573)
>>> PAPER.gnss.reported_sigmas()
(5.0, 1.0, 20.054)
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class GnssNoise:
    """Errors of the antenna position (ENU metres) and heading (rad), and what the fix claims."""

    white_h_m: float = 0.0
    """White noise per horizontal axis and fix, m."""
    white_v_m: float = 0.0
    white_heading_rad: float = 0.0
    bias_h_m: float = 0.0
    """Per-pass bias, std per horizontal axis, m."""
    bias_v_m: float = 0.0
    bias_heading_rad: float = 0.0
    walk_h_m_per_sqrt_s: float = 0.0
    """Random-walk drift of the bias per horizontal axis, m per sqrt(s)."""
    walk_v_m_per_sqrt_s: float = 0.0
    multipath_prob: float = 0.0
    """Share of fixes displaced horizontally by multipath."""
    multipath_min_m: float = 20.0
    multipath_max_m: float = 50.0
    reported_sigma_h_m: float | None = None
    """What the fix claims; None = the white level."""
    reported_sigma_v_m: float | None = None
    reported_sigma_heading_deg: float | None = None
    heading_from_track: bool = False
    """The fix's heading is the course over ground of the noisy fix track (the drive
    computes it), not the true heading plus ``heading_rad``."""

    def __post_init__(self) -> None:
        for name in (
            "white_h_m",
            "white_v_m",
            "white_heading_rad",
            "bias_h_m",
            "bias_v_m",
            "bias_heading_rad",
            "walk_h_m_per_sqrt_s",
            "walk_v_m_per_sqrt_s",
        ):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"GnssNoise.{name} must be >= 0")
        if not 0.0 <= self.multipath_prob <= 1.0:
            raise ValueError("GnssNoise.multipath_prob must be in [0, 1]")
        if not 0.0 <= self.multipath_min_m <= self.multipath_max_m:
            raise ValueError("GnssNoise: need 0 <= multipath_min_m <= multipath_max_m")

    def reported_sigmas(self) -> tuple[float, float, float]:
        """(sigma_h_m, sigma_v_m, sigma_heading_deg) written into every fix (> 0)."""
        h = self.white_h_m if self.reported_sigma_h_m is None else self.reported_sigma_h_m
        v = self.white_v_m if self.reported_sigma_v_m is None else self.reported_sigma_v_m
        hd = (
            float(np.degrees(self.white_heading_rad))
            if self.reported_sigma_heading_deg is None
            else self.reported_sigma_heading_deg
        )
        # A receiver never claims zero; floors keep observations valid on the wire.
        return max(h, 0.01), max(v, 0.01), round(max(hd, 1e-3), 3)

    def heading_sigma_deg(self, speed_mps: Array) -> Array:
        """Per fix, the heading sigma claimed: the same at every speed."""
        return np.full(np.shape(speed_mps), self.reported_sigmas()[2])

    def sample(self, rng: np.random.Generator, t: Array) -> GnssErrors:
        """Errors for one pass with fix times ``t`` (s, increasing)."""
        t = np.asarray(t, float)
        n = t.size
        bias0 = rng.normal(0.0, 1.0, 3) * np.array([self.bias_h_m, self.bias_h_m, self.bias_v_m])
        dt = np.diff(t, prepend=t[:1] if n else t)
        q = np.array([self.walk_h_m_per_sqrt_s, self.walk_h_m_per_sqrt_s, self.walk_v_m_per_sqrt_s])
        steps = rng.normal(0.0, 1.0, (n, 3)) * np.sqrt(np.maximum(dt, 0.0))[:, None] * q
        bias = bias0 + np.cumsum(steps, axis=0)
        sig_w = np.array([self.white_h_m, self.white_h_m, self.white_v_m])
        white = rng.normal(0.0, 1.0, (n, 3)) * sig_w
        multipath = rng.random(n) < self.multipath_prob
        mag = rng.uniform(self.multipath_min_m, self.multipath_max_m, n)
        ang = rng.uniform(0.0, 2.0 * np.pi, n)
        jump = np.zeros((n, 3))
        jump[:, 0] = np.where(multipath, mag * np.sin(ang), 0.0)
        jump[:, 1] = np.where(multipath, mag * np.cos(ang), 0.0)
        heading_bias = float(rng.normal(0.0, self.bias_heading_rad))
        heading = heading_bias + rng.normal(0.0, 1.0, n) * self.white_heading_rad
        return GnssErrors(
            bias_enu=bias,
            white_enu=white,
            multipath=multipath,
            multipath_enu=jump,
            heading_rad=heading,
            heading_bias_rad=heading_bias,
        )


@dataclass(frozen=True)
class GnssErrors:
    """The sampled GNSS error of one pass, by component (kept as ground truth)."""

    bias_enu: Array
    """(M, 3) per-pass bias plus its random walk, m."""
    white_enu: Array
    multipath: NDArray[np.bool_]
    multipath_enu: Array
    heading_rad: Array
    """(M,) total heading error, rad."""
    heading_bias_rad: float
    velocity_enu: Array | None = None
    """(M, 2) East and North velocity error at each fix, m/s, where the model has one (the
    replay: the logged error's rate over the second that holds the fix); None: a course
    over ground differentiates ``total_enu``."""

    @property
    def total_enu(self) -> Array:
        return self.bias_enu + self.white_enu + self.multipath_enu


@dataclass(frozen=True)
class DetectorNoise:
    """The simulated sign detector."""

    pixel_sigma: float = 0.0
    """Std of the box centre per axis, px."""
    size_sigma_px: float = 0.0
    """Std of the box's width and of its height, px (the centre keeps ``pixel_sigma``).
    0 keeps the true size: the box-size range then errs only by the panel's own size.
    The vehicle model assumes ``sqrt(2) * pixel_sigma`` on the height
    (:func:`vehicle.geoloc.box_range`)."""
    detection_prob: float = 1.0
    false_positive_rate: float = 0.0
    """Probability that an image holds one false positive."""
    score_range: tuple[float, float] = (0.5, 1.0)
    false_positive_score_range: tuple[float, float] = (0.3, 0.8)

    def __post_init__(self) -> None:
        for name in ("pixel_sigma", "size_sigma_px"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"DetectorNoise.{name} must be >= 0")
        for name in ("detection_prob", "false_positive_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"DetectorNoise.{name} must be in [0, 1]")


class GnssModel(Protocol):
    """What a drive needs of a GNSS error model (:class:`GnssNoise`, or
    :class:`fleetsim.gnss_replay.ReplayedGnss`)."""

    heading_from_track: bool

    def sample(self, rng: np.random.Generator, t: Array) -> GnssErrors: ...

    def reported_sigmas(self) -> tuple[float, float, float]: ...

    def heading_sigma_deg(self, speed_mps: Array) -> Array:
        """Per fix, the heading sigma claimed at its speed (m/s), degrees."""
        ...


@dataclass(frozen=True)
class NoiseModel:
    name: str
    gnss: GnssModel
    detector: DetectorNoise

    def without_noise(self) -> NoiseModel:
        """Same reported sigmas, every error and miss removed (for geometry checks)."""
        s_h, s_v, s_hd = self.gnss.reported_sigmas()
        return NoiseModel(
            f"{self.name}-exact",
            GnssNoise(
                reported_sigma_h_m=s_h, reported_sigma_v_m=s_v, reported_sigma_heading_deg=s_hd
            ),
            replace(self.detector, pixel_sigma=0.0, detection_prob=1.0, false_positive_rate=0.0),
        )


PAPER = NoiseModel(
    "paper",
    GnssNoise(white_h_m=5.0, white_heading_rad=0.35, reported_sigma_v_m=1.0),
    DetectorNoise(pixel_sigma=5.0),
)

FLEET = NoiseModel(
    "fleet",
    GnssNoise(
        white_h_m=1.0,
        white_v_m=1.5,
        white_heading_rad=0.01,
        bias_h_m=2.5,
        bias_v_m=3.5,
        bias_heading_rad=0.02,
        walk_h_m_per_sqrt_s=0.2,
        walk_v_m_per_sqrt_s=0.3,
        multipath_prob=0.03,
        multipath_min_m=20.0,
        multipath_max_m=50.0,
    ),
    DetectorNoise(pixel_sigma=3.0, detection_prob=0.8, false_positive_rate=0.02),
)

EXACT = FLEET.without_noise()
"""No error at all; the fix still claims FLEET's sigmas."""

PRESETS: dict[str, NoiseModel] = {"paper": PAPER, "fleet": FLEET, "exact": EXACT}
