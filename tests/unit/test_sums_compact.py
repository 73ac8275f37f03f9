"""Compacting the sums (dropping the rows of retired and merged landmarks, renumbering the
rest) changes no result: a script of new rows, rays in open and held passes, merges,
retirements, closings, releases and evictions gives, for every live landmark, the same
packed row and the same solution to the bit whether or not (and however often) the rows
were compacted on the way; quiet passes follow the renumbering."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums
from hdmap.mapping.quiet import QuietPasses, compact_rows
from tests.support.estimator import random_batch

HOLD = 9_001


class Lm:
    """A landmark as a service keeps one: an id and its sums row."""

    def __init__(self, lid: int, row: int) -> None:
        self.id, self.row = lid, row


def script(cfg: EstimatorConfig, compact_at: set[int], seed: int = 5):
    """Run the script; compact the rows (every dead one) after the steps in ``compact_at``.
    Returns the sums, the live landmarks by id and the quiet passes."""
    rng = np.random.default_rng(seed)
    sums = LandmarkSums(cfg, capacity=4)
    quiet = QuietPasses(after_s=100.0, clock=lambda: 0.0)
    live: dict[int, Lm] = {}
    next_id = 0
    for step in range(14):
        x0 = rng.normal(0, 20, (3, 3))
        for row in sums.new_rows(3, x0).tolist():
            live[next_id] = Lm(next_id, row)
            next_id += 1
        ids = sorted(live)
        pick = rng.integers(0, 7, 160)
        rows_local, clusters, rays, _xs = random_batch(rng, n_rows=7, n=160)
        lms = [live[ids[k % len(ids)]] for k in rows_local.tolist()]
        rows = np.array([lm.row for lm in lms], np.int64)
        clusters = clusters + 100 * step
        held = np.where(pick == 0, HOLD + step % 3, 0)
        clusters = np.where(held != 0, clusters + 50_000, clusters)  # held passes: own keys
        rays = replace(rays, weight=np.where(held != 0, 0.05, 1.0))
        sums.accumulate(rows, clusters, rays, hold=held)
        for lm, c in zip(lms, clusters.tolist(), strict=True):
            quiet.note(c, [(lm.id, lm.row)])
        if step % 2 == 1 and len(ids) > 3:  # a merge
            keep, drop = live[ids[1]], live[ids[-2]]
            sums.merge_rows(keep.row, drop.row, translation=[0.2, -0.1, 0.0])
            del live[drop.id]
        if step % 3 == 2:  # a retirement: the landmark goes, its row stays behind
            live.pop(ids[2], None)
        if step % 4 == 3:
            sums.release(HOLD + (step // 4) % 3, 0.7)
            sums.drop_held(HOLD + (step // 4 + 1) % 3)
            sums.close_passes(clusters=np.arange(100 * step - 200, 100 * step - 150))
        if step in compact_at:
            compact_rows(quiet, sums, live.values(), minimum=0, share=0.0)
            assert len(sums) == len(live)
    return sums, live, quiet


def state_of(sums: LandmarkSums, live: dict[int, Lm]) -> dict[int, tuple]:
    ids = sorted(live)
    rows = np.array([live[i].row for i in ids], np.int64)
    blobs = sums.pack_rows(rows)
    sol = sums.solve(rows, update_reference=False)
    return {
        i: (blobs[k], sol.x[k].tobytes(), sol.cov[k].tobytes(), bool(sol.ok[k]))
        for k, i in enumerate(ids)
    }


CONFIGS = {
    "default": EstimatorConfig(),
    "few_open": EstimatorConfig(max_open_passes=2),
}


@pytest.mark.parametrize("name", sorted(CONFIGS))
@pytest.mark.parametrize("compact_at", [{3}, {1, 5, 9, 12}, set(range(14))])
def test_compacted_rows_give_the_same_state_to_the_bit(name: str, compact_at: set[int]) -> None:
    cfg = CONFIGS[name]
    ref_sums, ref_live, _ = script(cfg, set())
    sums, live, quiet = script(cfg, compact_at)
    assert len(sums) < len(ref_sums)
    assert sorted(live) == sorted(ref_live)
    assert state_of(sums, live) == state_of(ref_sums, ref_live)
    # the open passes are the same (as landmark id, cluster) and quiet follows them
    lid_ref = {lm.row: i for i, lm in ref_live.items()}
    lid = {lm.row: i for i, lm in live.items()}
    open_ref = {(lid_ref[r], c) for r, c in ref_sums.open_passes() if r in lid_ref}
    assert {(lid[r], c) for r, c in sums.open_passes() if r in lid} == open_ref
    members = {m for _c, ms in quiet._open.items() for m in ms[1]}
    assert all(live[i].row == r for i, r in members if i in live)
    if 13 in compact_at:  # compacted last: only live landmarks' passes are left
        assert {i for i, _r in members} <= set(live)


def test_compaction_waits_for_as_many_dead_rows_as_live_and_the_minimum() -> None:
    sums = LandmarkSums(capacity=4)
    quiet = QuietPasses(after_s=10.0, clock=lambda: 0.0)
    lms = [Lm(i, r) for i, r in enumerate(sums.new_rows(6, np.zeros((6, 3))).tolist())]
    assert compact_rows(quiet, sums, lms[:3], minimum=0) is not None  # 3 dead, 3 live
    assert [lm.row for lm in lms[:3]] == [0, 1, 2] and len(sums) == 3
    assert compact_rows(quiet, sums, lms[:2], minimum=0) is None  # 1 dead, 2 live
    assert compact_rows(quiet, sums, lms[:1], minimum=3) is None  # 2 dead < 3
    assert compact_rows(quiet, sums, lms[:0], minimum=3) is not None and len(sums) == 0
