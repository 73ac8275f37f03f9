"""When a service may try again after transactions that failed on the storage
(:class:`Backoff`, the service's :attr:`~hdmap.runtime.service.Service.backoff`).

>>> b = Backoff(first_s=0.1, max_s=5.0)
>>> b.failed(10.0), b.failed(10.0), b.failed(10.0), b.waiting(10.1), b.fire(10.2)
(0.0, 0.1, 0.2, True, True)
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Backoff:
    """When a service may try again after transactions that failed on the storage.

    The first failure in a row may be retried at once (a passing lock, a blip); each
    further one waits ``first_s``, doubling up to ``max_s``; a commit resets it. Times are
    of the service's clock (:attr:`Service.clock`)."""

    first_s: float = 0.1
    max_s: float = 5.0
    failures: int = 0
    """Storage failures in a row (0 after a commit)."""
    retry_at: float | None = None
    """When the next try is due; None when none is owed (no failure, or the retry ran)."""

    def failed(self, now: float) -> float:
        """One more failure at ``now``: the wait before the next try (also kept)."""
        self.failures += 1
        delay = 0.0
        if self.failures > 1:
            delay = min(self.max_s, self.first_s * 2.0 ** (self.failures - 2))
        self.retry_at = now + delay
        return delay

    def succeeded(self) -> None:
        """A commit: no wait any more."""
        self.failures = 0
        self.retry_at = None

    def waiting(self, now: float) -> bool:
        """Whether a failed try is still being waited out at ``now``."""
        return self.retry_at is not None and now < self.retry_at

    def fire(self, now: float) -> bool:
        """Whether a retry is due at ``now``; if so it is taken (not due again until the
        next failure)."""
        if self.retry_at is None or now < self.retry_at:
            return False
        self.retry_at = None
        return True

    def wait_s(self, now: float) -> float:
        """Seconds until the retry (0 when none is waited for)."""
        return 0.0 if self.retry_at is None else max(0.0, self.retry_at - now)
