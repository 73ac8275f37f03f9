"""How a stage log is kept: how long a consumer waits for entries missing before live
ones (:class:`GapPolicy`, see :mod:`hdmap.runtime.stream`, "Gaps are bounded") and what
a producer keeps of its log (:class:`RetentionPolicy`, :mod:`hdmap.runtime.log_out`)."""

from __future__ import annotations

from dataclasses import dataclass

from hdmap.runtime.config import ConfigError


@dataclass(frozen=True)
class GapPolicy:
    """How a consumer waits for the entries missing before live ones (``[NAME.gaps]`` of a
    services config file). Times are of the consumer's clock (monotonic seconds)."""

    max_ahead: int = 10_000
    """Live entries held behind gaps, all tiles together; more are dropped (replayed)."""
    retry_s: float = 0.5
    """A gap a catch-up did not fill is asked for again after this, doubling per try."""
    retry_max_s: float = 30.0
    timeout_s: float = 30.0
    """A gap open this long is reported and the entries waiting behind it are dropped."""

    def __post_init__(self) -> None:
        if not (isinstance(self.max_ahead, int) and self.max_ahead >= 0):
            raise ConfigError("gaps.max_ahead: an integer >= 0")
        for name in ("retry_s", "retry_max_s", "timeout_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0.0 < v <= 86_400.0):
                raise ConfigError(f"gaps.{name}: seconds in (0, 86400]")


@dataclass(frozen=True)
class RetentionPolicy:
    """What a producer keeps of its log (``[NAME.retention]`` of a services config file):
    every entry some consumer that sent a mark has not applied, and every entry younger
    than ``retain_s``; the rest is deleted every ``every_s``. Wall-clock seconds."""

    retain_s: float = 86_400.0
    """The floor: entries younger than this stay whatever the marks say (a consumer that
    has not sent a mark yet, a new region, has this long to start)."""
    every_s: float = 60.0
    """How often the log is truncated."""
    forget_after_s: float = 7 * 86_400.0
    """A consumer silent this long no longer holds the log back (it must be rebuilt)."""

    def __post_init__(self) -> None:
        for name in ("retain_s", "every_s", "forget_after_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0.0 < v <= 10 * 365 * 86_400.0):
                raise ConfigError(f"retention.{name}: seconds in (0, 3650 days]")
