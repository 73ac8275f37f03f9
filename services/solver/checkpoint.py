"""The solver's update log folded into per-tile checkpoints as retention deletes it
(:mod:`hdmap.runtime.log_checkpoint`): each landmark's last published row, and the
removals. A new or rebuilt publisher that asks for entries the solver has deleted gets
the tiles' checkpoints and then the log's tail, and holds the map it would hold had it
read the whole log.

A checkpoint keeps the newest :data:`MAX_REMOVALS` removals of its tile: a consumer
restored from a backup older than that many removals may keep a landmark the map has
since removed (a fresh consumer never holds one).

>>> from schemas.tables import Landmarks, Removals
>>> import numpy as np
>>> def upd(ids, gone=()):
...     n = len(ids)
...     lm = Landmarks(np.array(ids, np.uint64), np.zeros(n, np.uint16), np.full(n, 60.0),
...                    np.full(n, 24.0), np.zeros(n), np.zeros((n, 6)), np.ones(n, np.uint8),
...                    np.ones(n, np.uint32), np.ones(n, np.uint32), np.array(ids, np.uint64),
...                    np.full(n, 1.7e9), np.full(n, 1.7e9))
...     rm = Removals(np.array(gone, np.uint64), np.array(gone, np.uint64))
...     return LandmarkUpdates(lm, rm).to_bytes()
>>> cp = LandmarkUpdates.from_bytes(fold_updates(None, [upd([1, 2]), upd([3], gone=[2])]))
>>> cp.landmarks.id.tolist(), cp.removed.id.tolist()
([1, 3], [2])
>>> back = fold_updates(cp.to_bytes(), [upd([], gone=[1]), upd([1])])  # 1 left, came back
>>> LandmarkUpdates.from_bytes(back).landmarks.id.tolist()
[3, 1]
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from schemas import LandmarkUpdates
from schemas.tables import Landmarks, Removals

MAX_REMOVALS = 4096
"""Removals a tile's checkpoint keeps (the newest)."""


def fold_updates(checkpoint: bytes | None, bodies: Sequence[bytes]) -> bytes:
    """The tile's checkpoint after ``bodies`` (update entries, in log order)."""
    parts = [LandmarkUpdates.from_bytes(b) for b in ([checkpoint] if checkpoint else [])]
    parts += [LandmarkUpdates.from_bytes(b) for b in bodies]
    rows = Landmarks.concat([p.landmarks for p in parts])
    removed = Removals.concat([p.removed for p in parts])
    # a landmark leaves a tile and may come back (its estimate moved): whichever of its
    # last row and its last removal came later decides
    row_at = np.repeat(np.arange(len(parts)), [len(p.landmarks) for p in parts])
    gone_at = np.repeat(np.arange(len(parts)), [len(p.removed) for p in parts])
    rows_last = _last_of_each(np.asarray(rows.id))
    gone_last = _last_of_each(np.asarray(removed.id))
    rid, gid = np.asarray(rows.id)[rows_last], np.asarray(removed.id)[gone_last]
    r_at, g_at = row_at[rows_last], gone_at[gone_last]
    keep_rows = rows_last[_after(rid, r_at, gid, g_at)]
    keep_gone = gone_last[_after(gid, g_at, rid, r_at)]
    keep_gone = keep_gone[max(0, len(keep_gone) - MAX_REMOVALS) :]
    return LandmarkUpdates(rows.take(keep_rows), removed.take(keep_gone)).to_bytes()


def _last_of_each(ids: np.ndarray) -> np.ndarray:
    """Index of each id's last occurrence, in order of occurrence."""
    _u, first_from_end = np.unique(ids[::-1], return_index=True)
    return np.sort(len(ids) - 1 - first_from_end).astype(np.int64)


def _after(ids: np.ndarray, at: np.ndarray, other: np.ndarray, other_at: np.ndarray) -> np.ndarray:
    """Whether each ``ids[k]`` at ``at[k]`` comes later than the same id in ``other``
    (unique ids, at ``other_at``); True where ``other`` does not have it."""
    order = np.argsort(other, kind="stable")
    o_ids, o_at = other[order], other_at[order]
    k = np.minimum(np.searchsorted(o_ids, ids), max(len(o_ids) - 1, 0))
    before = np.full(len(ids), -1, np.int64)
    if len(o_ids):
        hit = o_ids[k] == ids
        before[hit] = o_at[k[hit]]
    return at > before
