"""Counts per unordered pair of landmarks, listed by landmark, with the pairs changed since
the last save: how often two landmarks of one class were detected in one image
(co-visibility) or linked by one upload unit (co-passes).

>>> c = PairCounts()
>>> c.add(7, 3); c.add(3, 7, 2); c.add(3, 9)
>>> c.get(7, 3), c.get(3, 9), c.get(7, 9)
(3, 1, 0)
>>> c.pop(3), c.counts, sorted(c.dirty)
({7: 3, 9: 1}, {}, [(3, 7), (3, 9)])
"""

from __future__ import annotations

from collections import defaultdict


def pair_key(a: int, b: int) -> tuple[int, int]:
    """Key of an unordered pair of landmark ids."""
    return (a, b) if a < b else (b, a)


class PairCounts:
    """Counts by pair (``counts``, keyed ``(a, b)`` with ``a < b``); ``dirty`` names the pairs
    changed (or removed) since :meth:`clear_marks`."""

    def __init__(self) -> None:
        self.counts: dict[tuple[int, int], int] = {}
        self._of: dict[int, set[int]] = defaultdict(set)
        self.dirty: set[tuple[int, int]] = set()

    def add(self, a: int, b: int, n: int = 1) -> None:
        """``n`` more for the pair ``a``, ``b``."""
        k = pair_key(a, b)
        self.counts[k] = self.counts.get(k, 0) + n
        self._of[a].add(b)
        self._of[b].add(a)
        self.dirty.add(k)

    def get(self, a: int, b: int) -> int:
        """The pair's count (0 if never counted)."""
        return self.counts.get(pair_key(a, b), 0)

    def pop(self, lid: int) -> dict[int, int]:
        """Remove every pair of landmark ``lid``; returns other id -> count."""
        out = {}
        for other in sorted(self._of.pop(lid, set())):
            k = pair_key(lid, other)
            out[other] = self.counts.pop(k)
            self.dirty.add(k)
            self._of[other].discard(lid)
        return out

    def clear(self) -> None:
        """Forget every count (and the marks)."""
        self.counts.clear()
        self._of.clear()
        self.dirty.clear()

    def clear_marks(self) -> None:
        self.dirty.clear()
