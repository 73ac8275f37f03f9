"""How long a stage consumer waits for entries missing before live ones (see
:mod:`hdmap.runtime.stream`, "Gaps are bounded")."""

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
