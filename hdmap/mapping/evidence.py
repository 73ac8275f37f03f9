"""Which "not seen" reports may move a landmark's existence (issue 21 point 5): no single
vehicle can revoke signs, whether its camera is blind or it lies.

Three rules, each against a failure the fleet cannot tell from a removed sign alone:

- **Blind passes.** A pass that had at least ``min_expected`` landmarks in view and saw
  fewer than ``min_seen_share`` of them, or fewer than ``min_seen`` (off), reports its misses as
  nothing (a dirty lens, a camera pointed at the sky, a vehicle that reports "not seen"
  everywhere). Its seen landmarks still count. Pitfall: a pass past only one mapped sign,
  which is gone, is taken for blind too (the next passes, which see other signs, count).
- **A vehicle's misses are capped.** Of one landmark, a vehicle's misses count at most
  ``misses_per_vehicle`` times within ``window_s`` (event time) since the landmark was
  last detected: one vehicle driving the same street all day weighs like two passes. A
  detection refutes the misses before it: they no longer take from anyone's cap (else a
  vehicle's strays before a sign was taken down used up its say after).
- **Revocation needs several vehicles.** A landmark can be revoked only once misses from
  ``min_vehicles`` distinct vehicles have counted since it was last seen
  (:meth:`MissLedger.revocable`); a detection by anyone clears the list.

>>> p = EvidencePolicy()
>>> blind([True, False, False, False], p).tolist()  # saw 1 of 4 in view: blind
[True, True, True, True]
>>> strict = EvidencePolicy(min_seen=1)
>>> blind([False], strict).tolist(), blind([True, False], strict).tolist()  # saw none: blind
([True], [False, False])
>>> led = MissLedger(p)
>>> [led.admit(7, "veh-a", t, seen=False) for t in (0.0, 10.0, 20.0)]
[True, True, False]
>>> led.revocable(7), led.admit(7, "veh-b", 30.0, seen=False), led.revocable(7)
(False, True, True)
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class EvidencePolicy:
    min_expected: int = 3
    """A pass is judged blind only with at least this many landmarks in view."""
    min_seen_share: float = 0.5
    """A pass that saw less than this share of the landmarks it had in view is blind."""
    min_seen: int = 0
    """A pass that saw fewer landmarks than this is blind whatever it had in view (0: off).
    1 takes a blind camera that passes one or two mapped signs for blind too, but also a
    pass past one sign that is gone: on the changes evaluation (4 seeds) removal p95 19 ->
    40 passes with no fewer false revocations (0 either way; docs/experiments/
    2026-12-map-follows-world.md)."""
    misses_per_vehicle: int = 2
    """A vehicle's misses of one landmark that count within ``window_s``."""
    window_s: float = 86_400.0
    min_vehicles: int = 2
    """Distinct vehicles whose misses must have counted since the last detection."""

    def __post_init__(self) -> None:
        if not (0.0 <= self.min_seen_share <= 1.0 and self.min_expected >= 1):
            raise ValueError("evidence: min_seen_share in [0, 1], min_expected >= 1")
        if self.misses_per_vehicle < 1 or self.min_vehicles < 1 or self.window_s <= 0:
            raise ValueError("evidence: misses_per_vehicle, min_vehicles >= 1, window_s > 0")


def blind(seen: ArrayLike, policy: EvidencePolicy) -> NDArray[np.bool_]:
    """Per landmark a pass had in view (``seen``: whether it detected each), whether the
    pass is blind (the same for all: its misses are no evidence)."""
    s = np.asarray(seen, bool)
    few = s.size >= policy.min_expected and s.mean() < policy.min_seen_share
    return np.full(s.size, bool(s.size and (few or s.sum() < policy.min_seen)))


class MissLedger:
    """Per landmark: when each vehicle's counted misses were, and the vehicles whose misses
    counted since the last detection (the state the matcher keeps with each landmark)."""

    def __init__(self, policy: EvidencePolicy) -> None:
        self.policy = policy
        self._misses: defaultdict[int, dict[str, list[float]]] = defaultdict(dict)
        self._since_seen: defaultdict[int, set[str]] = defaultdict(set)

    def admit(self, landmark: int, vehicle: str, t: float, seen: bool) -> bool:
        """Whether this pass's evidence on ``landmark`` counts (a detection always does and
        clears the vehicles' misses; a miss within its vehicle's cap)."""
        if seen:
            self._since_seen.pop(landmark, None)
            self._misses.pop(landmark, None)
            return True
        mine = self._misses[landmark].setdefault(vehicle, [])
        mine[:] = [x for x in mine if t - x < self.policy.window_s]
        if len(mine) >= self.policy.misses_per_vehicle:
            return False
        mine.append(t)
        self._since_seen[landmark].add(vehicle)
        return True

    def revocable(self, landmark: int) -> bool:
        """Whether misses of enough distinct vehicles have counted since the last detection."""
        return len(self._since_seen.get(landmark, ())) >= self.policy.min_vehicles

    def forget(self, landmark: int) -> None:
        """The landmark is gone (revoked or merged): its records go with it."""
        self._misses.pop(landmark, None)
        self._since_seen.pop(landmark, None)

    def clear(self) -> None:
        self._misses.clear()
        self._since_seen.clear()

    def records(self, landmark: int) -> tuple[dict[str, list[float]], list[str]]:
        """One landmark's state: its counted misses by vehicle, the vehicles since seen."""
        return (
            {v: list(ts) for v, ts in sorted(self._misses.get(landmark, {}).items()) if ts},
            sorted(self._since_seen.get(landmark, ())),
        )

    def put(self, landmark: int, misses: dict[str, list[float]], since: list[str]) -> None:
        """Set one landmark's state (:meth:`records`), as a store reads it back."""
        self.forget(landmark)
        if misses:
            self._misses[landmark] = {v: list(ts) for v, ts in misses.items()}
        if since:
            self._since_seen[landmark] = set(since)

    def snapshot(self) -> dict[int, tuple[dict[str, list[float]], list[str]]]:
        """The state as plain data (landmark -> (misses by vehicle, vehicles since seen))."""
        keys = sorted(set(self._misses) | set(self._since_seen))
        return {
            k: (
                {v: list(ts) for v, ts in sorted(self._misses.get(k, {}).items())},
                sorted(self._since_seen.get(k, ())),
            )
            for k in keys
        }

    @classmethod
    def restore(cls, policy: EvidencePolicy, snap: dict) -> MissLedger:
        led = cls(policy)
        for k, (misses, since) in snap.items():
            led._misses[int(k)] = {v: list(ts) for v, ts in misses.items()}
            if since:
                led._since_seen[int(k)] = set(since)
        return led
