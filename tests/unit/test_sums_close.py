"""Passes closed in one ``accumulate`` call (evicted over ``max_open_passes``) are folded
together where their rows differ: the same state to the bit as folding them one by one."""

from __future__ import annotations

import numpy as np

from hdmap.mapping.estimator.model import EstimatorConfig
from hdmap.mapping.estimator.sums import LandmarkSums
from tests.support.estimator import random_batch


class OneByOne(LandmarkSums):
    """Every closed pass folded alone (what ``_close_many`` must equal)."""

    def _close_many(self, slots: list[int]) -> None:
        for slot in slots:
            self._close_detached(slot)


def test_passes_closed_together_fold_as_one_by_one() -> None:
    rng = np.random.default_rng(21)
    cfg = EstimatorConfig(max_open_passes=2)  # most calls close passes of several rows
    x0 = np.array([[5.0, 0.0, 2.5], [15.0, 5.0, 2.5], [25.0, -5.0, 2.5], [35.0, 0.0, 2.5]])
    together, alone = LandmarkSums(cfg), OneByOne(cfg)
    folded_together = 0
    close_many = together._close_many

    def counting(slots: list[int]) -> None:
        nonlocal folded_together
        rows = together._open.row[np.array(slots, np.int64)] if slots else np.zeros(0)
        folded_together += int(len(slots) > 1 and np.unique(rows).size == len(slots))
        close_many(slots)

    together._close_many = counting  # type: ignore[method-assign]
    for s in (together, alone):
        s.new_rows(4, x0)
    for _ in range(120):  # a few rays a call: its closes are mostly of distinct rows
        rows, clusters, r, _xs = random_batch(rng, n_rows=4, n=6)
        for s in (together, alone):
            s.accumulate(rows, clusters, r)
    assert folded_together > 0
    for name in LandmarkSums.ROW_ARRAYS:
        assert getattr(together, name).tobytes() == getattr(alone, name).tobytes(), name
    a, b = together.solve([0, 1, 2, 3], False), alone.solve([0, 1, 2, 3], False)
    assert a.x.tobytes() == b.x.tobytes() and a.cov.tobytes() == b.cov.tobytes()
