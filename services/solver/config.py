"""The solver's typed config (``[solver]`` in a services file)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from hdmap.mapping.estimator import EstimatorConfig
from hdmap.mapping.facing import FacingConfig
from hdmap.mapping.quiet import COMPACT_MIN_ROWS
from hdmap.runtime.config import ConfigError


@dataclass(frozen=True)
class SolverConfig:
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    provisional_passes: int = 2
    """Below the estimator's ``min_clusters`` a landmark is still published, as a
    'candidate', from this many passes on, if its information matrix is well-conditioned
    (its covariance then carries the pass-bias prior below; 0 disables)."""
    pass_bias_sigma_m: tuple[float, float, float] = (2.5, 2.5, 1.0)
    """Prior standard deviation (E, N, U) of the position error one pass shares by all its
    rays (GNSS bias): a candidate's covariance is at least this squared over its passes,
    since the between-pass spread of so few passes cannot measure it."""
    systematic_sigma_m: tuple[float, float, float] = (0.1, 0.1, 0.1)
    """Standard deviation (E, N, U) of the error more passes do not average away, added to
    the published covariance: the map floor (association mistakes, the pass weights' bias,
    geometry every car repeats). Measure it for a deployment against surveyed signs with
    ``hdmap calibrate-map`` (:mod:`hdmap.mapping.map_floor`); the fleet evaluation
    measures its own on held-out seeds (``fleetsim/data/map_floor.json``). The default,
    0.1 m, is what the fleet evaluation needed at 160 passes; at a few hundred passes a
    landmark needs more (docs/estimator.md section 12)."""
    pass_correlation: float = 0.0
    """``kappa``: the share of a pass's error that every pass of a landmark has in common
    (Kish's design effect, :func:`hdmap.mapping.map_floor.pass_correlation`); the
    published covariance is the between-pass covariance times ``1 + kappa G`` (``G`` its
    passes), before ``systematic_sigma_m`` and the shared floor are added. Measured
    against surveyed signs by ``hdmap calibrate-map``; 0: none. ConfigError naming the
    field if negative or not finite."""
    shared_floor_m2: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    """ENU covariance (ee, en, eu, nn, nu, uu; m^2) of the GNSS error a landmark's passes
    share, added to the published covariance in the landmark's local ENU: what more passes
    do not average away. Measured from a truth-referenced error log of the fleet's
    receivers by ``hdmap calibrate-gnss`` (:mod:`hdmap.mapping.gnss_floor`); 0 without
    one. Must be positive semi-definite (ConfigError naming the field)."""
    compact_min_rows: int = COMPACT_MIN_ROWS
    """The sums drop the rows of retired and merged landmarks once this many (and
    as many as live landmarks) have piled up, after a transaction's save
    (:func:`hdmap.mapping.quiet.compact_rows`, counted ``sums_rows_dropped``): memory
    follows the live map, not every landmark ever made. The map is the same to the bit
    whatever the value."""
    close_passes_after_s: float = 7200.0
    """Close a pass (``LandmarkSums.close_passes``) once no ray of it has come for this long
    (event time: the solver's clock, :meth:`SolverService.group_time`;
    :mod:`hdmap.mapping.quiet`); 0 keeps passes open until evicted
    (``max_open_passes`` per landmark). The estimate and covariance do not change (an open
    pass enters the solve exactly as a closed one); the stored state shrinks about
    threefold (BENCHMARKS.md "Scale"). Twice the matcher's ``pending_ttl_s``: a ray can be
    linked long after its upload (it waits in the matcher's pending pool until a landmark is
    initiated), and a ray of a pass already closed would start a new cluster, which changes
    the estimate (closing a vehicle's passes as soon as it uploads another costs seed 3 of
    the fleet evaluation precision, 1.000 -> 0.982). Passes close when the clock enters a
    new ``sweep_every_s`` period, so at the same entries live and on a replay. The
    bookkeeping is in memory: passes open at a restart count as quiet from the restored
    clock on (:func:`hdmap.mapping.quiet.note_open`)."""
    sweep_every_s: float = 60.0
    """Quiet passes are closed when the solver's clock enters a new period of this length
    (event time)."""
    confirm_max_sigma_m: float = 2.0
    """A landmark is published ``confirmed`` only while the larger horizontal standard
    deviation of its published covariance is at most this (m; ``inf``: no limit); past it,
    a ``candidate`` (published with its covariance all the same). A sign seen head-on down
    a street, or from a second street, can pass the conditioning test with its distance
    along the line of sight known to 5-30 m: four seeds of the fleet evaluation at 160
    passes, 25 of the 30 confirmed landmarks paired with no sign had a larger sigma above
    2 m, against 9 of the 584 paired ones with 50+ passes (with the real phone errors 56 of
    65, and 11 of 576). docs/estimator.md section 7."""
    panel_prior: Literal["off", "widen", "fuse"] = "widen"
    """What the catalogue's panel sizes do to a published landmark
    (:mod:`hdmap.mapping.box_ranges`; its rays' box ranges at its estimate say how large
    its panel is, and the catalogue says within ``estimator.panel_rel_sigma``): ``widen``
    (below); ``fuse``: the size is one measurement per landmark, an iterated Kalman
    update of the estimate and covariance along the line of sight
    (:func:`~hdmap.mapping.box_ranges.panel_update`); ``off``: neither."""
    range_check_k: float = 3.0
    """With ``panel_prior = "widen"``: a landmark whose rays' box ranges put their panel more than
    this many standard deviations from where its estimate is
    (:func:`hdmap.mapping.box_ranges.panel_discrepancy`: the rays' mean relative range at the
    estimate against the catalogue's nominal panel, with its size spread
    ``estimator.panel_rel_sigma`` and the estimate's own covariance along the line of sight)
    gets its covariance widened along the line of sight until the two agree within one (so it
    stays a candidate past ``confirm_max_sigma_m``); 0: no check. Bearings from one street fix a
    sign's distance poorly and the errors a street's passes share do not average out, so such a
    landmark can sit 6-19 m along its line of sight with a sigma under 2 m; a panel 3 standard
    deviations off its class's size is one in 370. Rays without a box range do not take part
    (docs/estimator.md section 7)."""
    loom_check_k: float = 3.0
    """A landmark whose rays' looming (how their boxes grow as the cars drive up;
    :func:`hdmap.mapping.looming.discrepancy`, free of the panel's size) puts its panel more
    than this many standard deviations along the line of sight from its estimate gets its
    covariance widened along the line of sight until the two agree within one (so it stays
    a candidate past ``confirm_max_sigma_m``); 0: no check. The standard deviation is the
    rays' white part, what the passes' shared position errors (measured;
    ``loom_pass_sigma_m``) do to the slope, and the estimate's own. Catches a sign seen
    from one street whose bearings put it 6-10 m along the street with a sigma under 2 m
    (the phones' street-level errors), which the panel's size alone cannot rule out
    (docs/estimator.md section 7). Pitfall: noise on the boxes' heights biases the slope
    (estimator section 7)."""
    loom_pass_sigma_m: float = 2.5
    """The prior (4 pseudo passes) of the passes' shared position error per axis the
    looming check measures per landmark from its passes' own slopes
    (:func:`hdmap.mapping.looming.shared_error`; 3.0 m measured on the simulated receiver,
    1.4 m on the phones' errors)."""
    facing_min_rays: int = FacingConfig.min_rays
    """Rays a landmark needs before its facing is published (:mod:`hdmap.mapping.facing`)."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.range_check_k) and self.range_check_k >= 0):
            raise ConfigError("solver.range_check_k: a finite number >= 0 (0: no check)")
        if not (np.isfinite(self.loom_check_k) and self.loom_check_k >= 0):
            raise ConfigError("solver.loom_check_k: a finite number >= 0 (0: no check)")
        if not (np.isfinite(self.loom_pass_sigma_m) and self.loom_pass_sigma_m >= 0):
            raise ConfigError("solver.loom_pass_sigma_m: a finite number of metres >= 0")
        if not self.confirm_max_sigma_m > 0:
            raise ConfigError("solver.confirm_max_sigma_m: a positive number of metres")
        if not (np.isfinite(self.pass_correlation) and self.pass_correlation >= 0):
            raise ConfigError("solver.pass_correlation: a finite number >= 0")
        if not all(np.isfinite(v) and v >= 0 for v in self.systematic_sigma_m):
            raise ConfigError("solver.systematic_sigma_m: three finite numbers >= 0 (E, N, U)")
        f = self.shared_floor_m2
        if len(f) != 6 or not np.isfinite(f).all():
            raise ConfigError("solver.shared_floor_m2: six finite numbers (ee en eu nn nu uu)")
        if np.linalg.eigvalsh(self.shared_floor())[0] < -1e-12:
            raise ConfigError("solver.shared_floor_m2: not positive semi-definite")

    def shared_floor(self) -> np.ndarray:
        """:attr:`shared_floor_m2` as a (3, 3) ENU matrix."""
        ee, en, eu, nn, nu, uu = (float(v) for v in self.shared_floor_m2)
        return np.array([[ee, en, eu], [en, nn, nu], [eu, nu, uu]])
