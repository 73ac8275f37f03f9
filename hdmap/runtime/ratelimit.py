"""Token buckets: the arithmetic of every rate limit (ingest's per-vehicle uploads, the
publisher's per-client snapshots).

Time is passed in by the caller (an injected clock), so the arithmetic is tested without
sleeping. A bucket is not thread-safe: its owner serialises the calls (ingest calls it on
its worker only, the publisher's snapshot limiter under its lock).

>>> t = [0.0]
>>> b = TokenBucket(rate=2.0, capacity=4.0, now=t[0])
>>> [b.take(1.0, t[0]) for _ in range(5)]  # a burst of 4, then wait 0.5 s for the 5th
[0.0, 0.0, 0.0, 0.0, 0.5]
>>> t[0] = 0.5
>>> b.take(1.0, t[0])
0.0
"""

from __future__ import annotations

from schemas.messages import MAX_RETRY_AFTER_S

__all__ = ["MAX_RETRY_AFTER_S", "TokenBucket"]


class TokenBucket:
    """``capacity`` tokens, refilled at ``rate`` per second.

    :meth:`take` grants a request when the bucket holds ``min(cost, capacity)`` tokens
    and then charges the full ``cost``: a request larger than the bucket is possible
    after an idle period and leaves the bucket in debt, so the long-run rate is exact.
    Invariant: ``tokens <= capacity``; ``tokens`` is negative only after such a request.
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

    def refund(self, cost: float) -> None:
        """Give back ``cost`` tokens a granted request did not use (a later check refused
        it), never beyond the capacity."""
        self.tokens = min(self.capacity, self.tokens + cost)
