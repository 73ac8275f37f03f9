"""Per-vehicle rate limits for ingest: token buckets on uploads/s and observations/s.

A vehicle that floods uploads is refused (``UploadAck.error.field == "rate"`` with
``retry_after_s``) without slowing anyone else: every vehicle has its own buckets, and a
refused upload costs ingest no decoding and no storage. The buckets are
:class:`hdmap.runtime.ratelimit.TokenBucket` (shared with the publisher's snapshot
limits); time comes from an injected clock, so the arithmetic is tested without sleeping.

>>> t = [0.0]
>>> lim = VehicleLimiter(RateLimit(uploads_per_s=2.0, upload_burst=4.0), lambda: t[0])
>>> [lim.upload("v") for _ in range(5)]  # a burst of 4, then wait 0.5 s for the 5th
[0.0, 0.0, 0.0, 0.0, 0.5]
>>> t[0] = 0.5
>>> lim.upload("v"), lim.upload("w")
(0.0, 0.0)
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from hdmap.runtime.config import ConfigError
from hdmap.runtime.ratelimit import TokenBucket


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
    new_vehicles_per_s: float = 5.0
    """Vehicles ingest has never recorded anything from, admitted per second over all
    vehicles (a client inventing a new vehicle id for every upload gets no more)."""
    new_vehicle_burst: float = 50.0
    """New vehicles admitted at once after a quiet period (a fleet starting together).
    Each new vehicle's first upload is at least one matcher unit (~5 ms of its CPU), so a
    burst of B delays the map by about B x 5 ms for everyone."""

    def __post_init__(self) -> None:
        for name in (
            "observations_per_s",
            "observation_burst",
            "uploads_per_s",
            "upload_burst",
            "new_vehicles_per_s",
            "new_vehicle_burst",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"rate_limit.{name}: must be a finite number >= 0, got {v}")
        if self.observations_per_s > 0 and self.observation_burst < 1:
            raise ConfigError("rate_limit.observation_burst: must be >= 1")
        if self.uploads_per_s > 0 and self.upload_burst < 1:
            raise ConfigError("rate_limit.upload_burst: must be >= 1")
        if self.new_vehicles_per_s > 0 and self.new_vehicle_burst < 1:
            raise ConfigError("rate_limit.new_vehicle_burst: must be >= 1")
        if self.max_vehicles < 1:
            raise ConfigError("rate_limit.max_vehicles: must be >= 1")


class VehicleLimiter:
    """The buckets of every vehicle seen recently (worker thread only: not thread-safe)."""

    def __init__(self, limit: RateLimit, clock: Callable[[], float] = time.monotonic):
        self.limit = limit
        self.clock = clock
        self._uploads: OrderedDict[str, TokenBucket] = OrderedDict()
        self._obs: OrderedDict[str, TokenBucket] = OrderedDict()
        self._known: OrderedDict[str, None] = OrderedDict()
        self._newcomers = (
            TokenBucket(limit.new_vehicles_per_s, limit.new_vehicle_burst, clock())
            if limit.new_vehicles_per_s > 0
            else None
        )

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

    def newcomer(self, vehicle: str, recorded: Callable[[str], bool]) -> float:
        """0.0 if ``vehicle`` may upload as far as admission goes, else seconds to wait. A
        vehicle is known once ingest recorded something from it (``recorded``: a lookup
        in ingest's database, made once per vehicle while it stays in memory); any other
        takes one token of the budget shared by all new vehicles."""
        if self._newcomers is None or vehicle in self._known:
            if vehicle in self._known:
                self._known.move_to_end(vehicle)
            return 0.0
        if recorded(vehicle):
            self.admitted(vehicle)
            return 0.0
        return self._newcomers.take(1.0, self.clock())

    def admitted(self, vehicle: str) -> None:
        """``vehicle`` has a recorded upload now: it is not new again."""
        self._known[vehicle] = None
        self._known.move_to_end(vehicle)
        while len(self._known) > self.limit.max_vehicles:
            self._known.popitem(last=False)

    def __len__(self) -> int:
        return len(self._uploads.keys() | self._obs.keys())
