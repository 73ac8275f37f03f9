"""Per-vehicle rate limits for ingest: token buckets on uploads/s and observations/s.

A vehicle that floods uploads is refused (``UploadAck.error.field == "rate"`` with
``retry_after_s``) without slowing anyone else: every vehicle has its own buckets, and a
refused upload costs ingest no decoding and no storage. Time comes from an injected
clock, so the arithmetic is tested without sleeping.

>>> t = [0.0]
>>> b = TokenBucket(rate=2.0, capacity=4.0, now=t[0])
>>> [b.take(1.0, t[0]) for _ in range(5)]  # a burst of 4, then wait 0.5 s for the 5th
[0.0, 0.0, 0.0, 0.0, 0.5]
>>> t[0] = 0.5
>>> b.take(1.0, t[0])
0.0
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from hdmap.runtime.config import ConfigError


@dataclass(frozen=True)
class RateLimit:
    """Per-vehicle limits (``[ingest.rate_limit]``); a rate of 0 disables that limit."""

    observations_per_s: float = 2000.0
    """Sustained observations per second one vehicle may upload (rows of its batches)."""
    observation_burst: float = 20000.0
    """Observations a vehicle may upload at once after being idle (bucket capacity)."""
    uploads_per_s: float = 20.0
    """Sustained upload requests per second one vehicle may make."""
    upload_burst: float = 100.0
    """Upload requests a vehicle may make at once after being idle."""
    max_vehicles: int = 100_000
    """Buckets kept in memory; beyond this the least recently seen vehicle is forgotten
    (an idle vehicle's bucket is full, so forgetting it changes nothing)."""

    def __post_init__(self) -> None:
        for name in ("observations_per_s", "observation_burst", "uploads_per_s", "upload_burst"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"rate_limit.{name}: must be a finite number >= 0, got {v}")
        if self.observations_per_s > 0 and self.observation_burst < 1:
            raise ConfigError("rate_limit.observation_burst: must be >= 1")
        if self.uploads_per_s > 0 and self.upload_burst < 1:
            raise ConfigError("rate_limit.upload_burst: must be >= 1")
        if self.max_vehicles < 1:
            raise ConfigError("rate_limit.max_vehicles: must be >= 1")


MAX_RETRY_AFTER_S = 86400.0
"""Upper bound of ``UploadAck.retry_after_s`` (schemas/README.md)."""


class TokenBucket:
    """``capacity`` tokens, refilled at ``rate`` per second.

    :meth:`take` grants a request when the bucket holds ``min(cost, capacity)`` tokens
    and then charges the full ``cost``: a request larger than the bucket is possible
    after an idle period and leaves the bucket in debt, so the long-run rate is exact.
    """

    def __init__(self, rate: float, capacity: float, now: float):
        if rate <= 0 or capacity <= 0:
            raise ValueError("a token bucket needs rate > 0 and capacity > 0")
        self.rate = rate
        self.capacity = capacity
        self.tokens = capacity
        self.stamp = now

    def _refill(self, now: float) -> None:
        if now > self.stamp:  # a clock that goes backwards refills nothing
            self.tokens = min(self.capacity, self.tokens + (now - self.stamp) * self.rate)
            self.stamp = now

    def take(self, cost: float, now: float) -> float:
        """Charge ``cost`` tokens and return 0.0, or return the seconds to wait (nothing
        charged) until the request would be granted."""
        self._refill(now)
        need = min(cost, self.capacity)
        if self.tokens >= need * (1.0 - 1e-9):  # waiting the given delay is always enough
            self.tokens -= cost
            return 0.0
        return min(MAX_RETRY_AFTER_S, (need - self.tokens) / self.rate)


class VehicleLimiter:
    """The buckets of every vehicle seen recently (worker thread only: not thread-safe)."""

    def __init__(self, limit: RateLimit, clock: Callable[[], float] = time.monotonic):
        self.limit = limit
        self.clock = clock
        self._uploads: OrderedDict[str, TokenBucket] = OrderedDict()
        self._obs: OrderedDict[str, TokenBucket] = OrderedDict()

    def _bucket(
        self, table: OrderedDict[str, TokenBucket], vehicle: str, rate: float, burst: float
    ) -> TokenBucket:
        now = self.clock()
        b = table.get(vehicle)
        if b is None:
            b = table[vehicle] = TokenBucket(rate, burst, now)
            while len(table) > self.limit.max_vehicles:
                table.popitem(last=False)
        else:
            table.move_to_end(vehicle)
        return b

    def upload(self, vehicle: str) -> float:
        """One upload request of ``vehicle``: 0.0 if allowed, else seconds to wait."""
        lim = self.limit
        if lim.uploads_per_s <= 0:
            return 0.0
        b = self._bucket(self._uploads, vehicle, lim.uploads_per_s, lim.upload_burst)
        return b.take(1.0, self.clock())

    def observations(self, vehicle: str, n: int) -> float:
        """``n`` observations of ``vehicle``: 0.0 if allowed, else seconds to wait."""
        lim = self.limit
        if lim.observations_per_s <= 0 or n <= 0:
            return 0.0
        b = self._bucket(self._obs, vehicle, lim.observations_per_s, lim.observation_burst)
        return b.take(float(n), self.clock())

    def __len__(self) -> int:
        return len(self._uploads.keys() | self._obs.keys())
