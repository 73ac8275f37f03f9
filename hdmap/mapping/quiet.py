"""Which open passes have been quiet long enough to close.

A service keeps a pass open in :class:`~hdmap.mapping.estimator.LandmarkSums` while more of its rays
may come, and closes it (``close_passes(rows, clusters)``) once no ray of it has come for
``after_s``. Closing changes neither the estimate nor the covariance; it keeps the stored
state to the closed sums. A ray of a pass already closed would start a new cluster (which
does change the estimate), so ``after_s`` must exceed the longest a ray can wait before it
is linked: the matcher's pending TTL. Both are event time (the clock a service is given:
the rays' capture times, :mod:`hdmap.mapping.event_time`), so a service catching up on
hours of log in minutes closes what live processing closed, no more.

>>> t = [0.0]
>>> q = QuietPasses(after_s=100.0, clock=lambda: t[0])
>>> q.note(7, [(1, 10), (2, 11)])          # pass 7 touched landmarks 1 and 2 (rows 10, 11)
>>> t[0] = 50.0; q.note(8, [(1, 10)])
>>> t[0] = 120.0; q.due()                  # pass 7 quiet since 0, pass 8 since 50
[(7, [(1, 10), (2, 11)])]
>>> t[0] = 130.0; q.note(8, [(3, 12)])     # more of pass 8: quiet from 130 on
>>> t[0] = 200.0; q.due(), len(q)
([], 1)
>>> off = QuietPasses(after_s=0.0); off.note(7, [(1, 10)]); off.due(), len(off)
([], 0)
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from typing import Any, Protocol

import numpy as np

from hdmap.mapping.estimator import LandmarkSums


class QuietPasses:
    """Open passes by when their last ray came; ``due`` hands out the quiet ones.
    ``after_s`` <= 0 turns it off: nothing is noted, nothing is ever due."""

    def __init__(self, after_s: float, clock: Callable[[], float] = time.monotonic):
        self.after_s = float(after_s)
        self._clock = clock
        self._open: OrderedDict[int, tuple[float, set[tuple[int, int]]]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._open)

    def note(self, key: int, members: Iterable[tuple[int, int]]) -> None:
        """Pass ``key`` got rays now on ``members`` ((landmark id, sums row))."""
        if self.after_s <= 0:
            return
        _, mine = self._open.pop(int(key), (0.0, set()))
        mine.update((int(a), int(b)) for a, b in members)
        self._open[int(key)] = (self._clock(), mine)  # to the end: the most recent

    def members(self, key: int) -> set[int]:
        """The landmarks pass ``key`` has linked rays to while open (ids; empty when it is
        not open, or when the closing is off and nothing is noted)."""
        known = self._open.get(int(key))
        return set() if known is None else {lid for lid, _row in known[1]}

    def extend(self, key: int, members: Iterable[tuple[int, int]]) -> None:
        """Pass ``key`` is open on ``members`` too (a merge moved it there), keeping its
        quiet time; a pass not known here is noted now.

        >>> t = [0.0]
        >>> q = QuietPasses(after_s=100.0, clock=lambda: t[0])
        >>> q.note(7, [(1, 10)]); t[0] = 60.0; q.extend(7, [(2, 11)]); q.extend(8, [(2, 11)])
        >>> t[0] = 120.0; q.due()
        [(7, [(1, 10), (2, 11)])]
        """
        if self.after_s <= 0:
            return
        known = self._open.get(int(key))
        if known is None:
            self.note(key, members)
        else:
            known[1].update((int(a), int(b)) for a, b in members)

    def due(self) -> list[tuple[int, list[tuple[int, int]]]]:
        """Passes quiet for ``after_s`` (forgotten here), oldest first."""
        out = []
        cutoff = self._clock() - self.after_s
        while self._open and next(iter(self._open.values()))[0] < cutoff:
            key, (_, mine) = self._open.popitem(last=False)
            out.append((key, sorted(mine)))
        return out

    def clear(self) -> None:
        self._open.clear()

    def renumber(self, new_of: np.ndarray) -> None:
        """The sums rows were renumbered (:meth:`LandmarkSums.compact`): members follow,
        those of gone rows are forgotten (and passes left with none), times kept."""
        for key in list(self._open):
            at, mine = self._open[key]
            kept = {(lid, int(new_of[row])) for lid, row in mine if new_of[row] >= 0}
            if kept:
                self._open[key] = (at, kept)
            else:
                del self._open[key]


class SweepPeriods:
    """Whether an event-time clock has entered a new period of ``every_s`` since the last
    sweep: the matcher's and the solver's timers run at the entry that moved the clock
    there, so at the same entry live and on a replay (:mod:`hdmap.mapping.event_time`).
    ``every_s`` <= 0: one period for ever (nothing is ever due).

    >>> s = SweepPeriods(60.0); s.restart(100.0)
    >>> s.due(110.0), s.due(125.0), s.due(125.0), s.due(300.0)
    (False, True, False, True)
    """

    def __init__(self, every_s: float):
        self.every_s = float(every_s)
        self._last = 0

    def _period(self, t: float) -> int:
        return int(t // self.every_s) if self.every_s > 0 else 0

    def restart(self, t: float) -> None:
        """After a (re)load at clock ``t``: the entry that moved it there has swept."""
        self._last = self._period(t)

    def due(self, t: float) -> bool:
        """The clock is at ``t``: whether that is a new period (then it counts as swept)."""
        p = self._period(t)
        if p == self._last:
            return False
        self._last = p
        return True


class _State(Protocol):
    """A service's landmark table: ``landmarks`` by id (with ``.row``) and ``put`` to save."""

    landmarks: dict[int, Any]

    def put(self, lm: Any) -> None: ...


def note_open(quiet: QuietPasses, sums: LandmarkSums, state: _State) -> int:
    """After a (re)load: every pass still open in ``sums`` is quiet from now on (its last
    ray's time is not stored), so it closes ``after_s`` later unless more rays come,
    rather than staying open until evicted. Returns how many were noted."""
    if quiet.after_s <= 0:
        return 0
    lid_of = {lm.row: lid for lid, lm in state.landmarks.items()}
    n = 0
    for row, cluster in sums.open_passes():
        lid = lid_of.get(row)
        if lid is not None:
            quiet.note(cluster, [(lid, row)])
            n += 1
    return n


def merge_rows(
    quiet: QuietPasses, sums: LandmarkSums, keep: Any, drop: Any, rotation: Any, translation: Any
) -> None:
    """:meth:`LandmarkSums.merge_rows` of landmark ``drop`` into ``keep`` (each with ``.id``,
    ``.row``); ``drop``'s open passes move onto ``keep`` and close with the rest of their
    pass (:meth:`QuietPasses.extend`), not only by eviction."""
    moved = sums.open_clusters(drop.row)
    sums.merge_rows(keep.row, drop.row, rotation, translation)
    for c in moved:
        quiet.extend(c, [(keep.id, keep.row)])


COMPACT_MIN_ROWS = 1024
"""Gone landmarks' rows a service's sums keep before :func:`compact_rows` drops them (and
at least as many as there are live ones: amortised O(1) a row)."""


def compact_rows(
    quiet: QuietPasses,
    sums: LandmarkSums,
    landmarks: Iterable[Any],
    minimum: int = COMPACT_MIN_ROWS,
    share: float = 1.0,
) -> np.ndarray | None:
    """Drop the rows of ``sums`` no landmark of ``landmarks`` (each with ``.row``, which is
    renumbered in place) holds, once there are ``minimum`` of them and ``share`` times as
    many as live rows; ``quiet`` follows. Returns the renumbering (old row -> new, -1:
    gone) or None.
    Nothing else may hold rows across the call (flush held links first, or renumber them
    with the result). Without it a long run's memory grows with every landmark ever
    retired or merged; with it, the results are the same to the bit."""
    lms = list(landmarks)
    dead = len(sums) - len(lms)
    if dead <= 0 or dead < max(share * len(lms), minimum):
        return None
    new_of = sums.compact(np.array([lm.row for lm in lms], np.int64))
    for lm in lms:
        lm.row = int(new_of[lm.row])
    quiet.renumber(new_of)
    return new_of


def close_quiet(quiet: QuietPasses, sums: LandmarkSums, state: _State) -> int:
    """Close the passes ``quiet`` says are due on the landmarks still there with the same
    row (a merged or retired one took its sums with it), marking them changed in ``state``.
    Returns how many (landmark, pass) were closed."""
    rows: list[int] = []
    clusters: list[int] = []
    for key, members in quiet.due():
        for lid, row in members:
            lm = state.landmarks.get(lid)
            if lm is not None and lm.row == row:
                rows.append(row)
                clusters.append(key)
                state.put(lm)  # its packed sums change
    return sums.close_passes(rows, clusters) if rows else 0
