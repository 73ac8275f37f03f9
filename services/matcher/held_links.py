"""The matcher's held links on disk: the links a gating tick made that are not in the
gating sums yet (:attr:`hdmap.mapping.matching.Matching.unsummed`).

A unit's links are held and added to the gating sums in one call when the sums are next
read (at the latest when its tick ends: :meth:`~hdmap.mapping.matching.Matching.
flush_links`). A transaction therefore saves the held links it made, as they are, instead
of adding them and packing the touched rows (what every small live batch paid); a restart
reloads the rows as last packed and holds the saved links again, in their order, which
gives the sums to the bit (the sums after a list of rays do not depend on how the list is
cut into ``accumulate`` calls).

Invariant: the table ``held_links`` holds, in order, exactly the links held in memory
after the last committed transaction; a flush empties it (:func:`save`).
"""

from __future__ import annotations

import sqlite3
from typing import Any

import numpy as np

from hdmap.mapping.estimator import Rays

SCHEMA = """
CREATE TABLE IF NOT EXISTS held_links (
    seq INTEGER PRIMARY KEY, n INTEGER NOT NULL, flags INTEGER NOT NULL,
    ints BLOB NOT NULL, floats BLOB NOT NULL);
"""

_WEIGHT, _RANGE = 1, 2

Held = tuple[Any, Any, Rays, Any]
"""(landmark rows, pass keys, rays, hold keys) of one :func:`~hdmap.mapping.linking.link`
call's landmarks of one home tile."""


def pack(ids: np.ndarray, item: Held) -> tuple[int, int, bytes, bytes]:
    """(n, flags, int64 columns, float64 columns) of one held item, its rows kept as the
    landmark ids ``ids`` (rows are numbered anew when the sums are reloaded)."""
    _rows, keys, rays, hold = item
    n = len(rays)
    flags = _WEIGHT if rays.weight is not None else 0
    flags |= _RANGE if rays.range_m is not None else 0
    ints = np.concatenate(
        [
            np.asarray(ids, np.uint64).reshape(n).view(np.int64),
            np.asarray(keys, np.int64).reshape(n),
            np.asarray(hold, np.int64).reshape(n),
        ]
    ).astype("<i8")
    cols = [
        np.asarray(rays.origin, float).reshape(n, 3),
        np.asarray(rays.direction, float).reshape(n, 3),
    ]
    for a in (rays.sigma_az, rays.sigma_el, rays.sigma_pos_h, rays.sigma_pos_v):
        cols.append(np.broadcast_to(np.asarray(a, float), (n,)).reshape(n, 1))
    if rays.weight is not None:
        cols.append(np.asarray(rays.weight, float).reshape(n, 1))
    if rays.range_m is not None:
        cols.append(np.asarray(rays.range_m, float).reshape(n, 1))
        cols.append(np.asarray(rays.sigma_range_m, float).reshape(n, 1))
    return n, flags, ints.tobytes(), np.hstack(cols).astype("<f8").tobytes()


def unpack(n: int, flags: int, ints: bytes, floats: bytes) -> tuple[np.ndarray, Held]:
    """The landmark ids and the held item :func:`pack` wrote (its rows still to be filled
    in from the ids: zeros)."""
    i = np.frombuffer(ints, "<i8").astype(np.int64).reshape(3, n)
    f = np.frombuffer(floats, "<f8").astype(float).reshape(n, -1)
    k = 10
    weight = None
    if flags & _WEIGHT:
        weight, k = f[:, k].copy(), k + 1
    range_m = sigma_range = None
    if flags & _RANGE:
        range_m, sigma_range = f[:, k].copy(), f[:, k + 1].copy()
    rays = Rays(
        f[:, 0:3].copy(),
        f[:, 3:6].copy(),
        f[:, 6].copy(),
        f[:, 7].copy(),
        f[:, 8].copy(),
        f[:, 9].copy(),
        weight,
        range_m,
        sigma_range,
    )
    ids = i[0].copy().view(np.uint64)
    return ids, (np.zeros(n, np.int64), i[1].copy(), rays, i[2].copy())


def save(
    conn: sqlite3.Connection,
    flushed: bool,
    start: int,
    new: list[tuple[np.ndarray, Held]],
) -> None:
    """Write the held links of a transaction: ``flushed``, the sums took the held links
    (the table empties first); ``new``, (landmark ids, item) of the links held since the
    last save, at positions from ``start`` on."""
    if flushed:
        conn.execute("DELETE FROM held_links")
    conn.executemany(
        "INSERT OR REPLACE INTO held_links(seq, n, flags, ints, floats) VALUES (?,?,?,?,?)",
        [(start + k, *pack(ids, item)) for k, (ids, item) in enumerate(new)],
    )


def load(conn: sqlite3.Connection, row_of: dict[int, int]) -> list[tuple[np.ndarray, Held]]:
    """The held links, in their order, with the rows ``row_of`` gives their landmark ids."""
    out = []
    for n, flags, ints, floats in conn.execute(
        "SELECT n, flags, ints, floats FROM held_links ORDER BY seq"
    ):
        ids, (_rows, keys, rays, hold) = unpack(int(n), int(flags), ints, floats)
        rows = np.array([row_of[int(i)] for i in ids.tolist()], np.int64)
        out.append((ids, (rows, keys, rays, hold)))
    return out
