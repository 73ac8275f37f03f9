"""Byte layout of a packed landmark state (:meth:`LandmarkSums.pack_rows
<hdmap.mapping.estimator.sums.LandmarkSums.pack_rows>` / ``unpack_rows``).

A blob is one version byte, one row record (the closed sums, the reference and the
count ``n_open`` of open passes) and ``n_open`` open-pass records: little-endian numpy
structured records without padding. Per version, with their sizes in bytes:

=======  =================  ==================  ============================================
version  row record         open-pass record    new in this version
=======  =================  ==================  ============================================
7        ROW_DTYPE 588      OPEN_DTYPE 448      inverse form: box-noise sums ``q2``, ``k``
6        ROW_DTYPE_V5 572   OPEN_DTYPE_V6 224   open passes' range scale sums ``t5``
5        ROW_DTYPE_V5 572   OPEN_DTYPE_V5 184   the pull sum ``c1`` (row and open passes)
4        ROW_DTYPE_V4 564   OPEN_DTYPE_V4 176   held passes (``w2``, ``hold``, ``j6``)
3        ROW_DTYPE_V4 564   OPEN_DTYPE_V3 112   ray weight sums (``w1``, ``w2``; ``w``)
2        ROW_DTYPE_V2 548   OPEN_DTYPE_V2 104   pass weighting (``s2``)
1        ROW_DTYPE_V2 548   OPEN_DTYPE_V1 96
=======  =================  ==================  ============================================

So a row packs to 565 bytes plus 176 per open pass, or, where it keeps a pull
(``EstimatorConfig.extra_sigma_pos_m`` set), 573 plus 184, or, where an open pass keeps
range scale sums (``EstimatorConfig.box_range`` with ``range_scale="per_pass"``), 573 plus
224, or, in the inverse-range form (``range_scale="inverse"``), 589 plus 448:
``pack_rows`` writes version 7 only for rows with box-noise sums, 6 for rows with range
scale sums, 5 for rows with a pull,
version 4 otherwise (8 bytes less per row and per open pass, which
keeps two rows with 8 open passes in one SQLite page). Versions 1-6 load as well, each
with its own row and open-pass records (:data:`OLD_PACK_VERSIONS` says what
``unpack_rows`` fills in). Bytes after the last open record are ignored; a negative
``n_open`` is refused.

>>> layout(4).row.itemsize, layout(4).open.itemsize
(564, 176)
>>> layout(5).row.itemsize - layout(4).row.itemsize
8
>>> layout(5).open.itemsize - layout(4).open.itemsize == 8
True
>>> rec = np.zeros((), ROW_DTYPE)
>>> rec["n_open"] = 2
>>> blob = encode(layout(7), rec, np.zeros(2, OPEN_DTYPE))
>>> len(blob) == 1 + 588 + 2 * 448
True
>>> lay, rec, op = decode(blob)
>>> lay.version, int(rec["n_open"]), op.dtype == OPEN_DTYPE, len(op)
(7, 2, True, 2)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

PACK_VERSION = 7
OLD_PACK_VERSIONS = (1, 2, 3, 4, 5, 6)
"""Version 1 kept open passes' raw sums in ``A`` and ``b`` as well; they are taken out
on load (its closed passes keep their unweighted sums; its open passes had no angular
variance sum: treated as precise). Versions 1 and 2 had no ray weight sums: taken as
weights of 1. Versions 1-3 had no held passes. Versions 1-4 had no pull sum (0). Versions
1-5 had no range scale sums (0), versions 1-6 no box-noise sums (0)."""

ROW_DTYPE_V2 = np.dtype(
    [
        ("anchor", "<f8", 3),
        ("x_ref", "<f8", 3),
        ("a6", "<f8", 6),
        ("j6", "<f8", 6),
        ("b", "<f8", 3),
        ("saa", "<f8", 21),
        ("sab", "<f8", 18),
        ("sbb", "<f8", 6),
        ("n_obs", "<i8"),
        ("n_closed", "<i8"),
        ("n_open", "<i4"),
    ]
)
ROW_DTYPE_V4 = np.dtype([*ROW_DTYPE_V2.descr, ("w1", "<f8"), ("w2", "<f8")])
ROW_DTYPE_V5 = np.dtype([*ROW_DTYPE_V4.descr, ("c1", "<f8")])
ROW_DTYPE = np.dtype([*ROW_DTYPE_V5.descr, ("q2", "<f8", 2)])
OPEN_DTYPE_V3 = np.dtype(
    [
        ("cluster", "<i8"),
        ("last", "<i8"),
        ("n", "<i8"),
        ("a6", "<f8", 6),
        ("b", "<f8", 3),
        ("s2", "<f8"),
        ("w", "<f8"),
    ]
)
OPEN_DTYPE_V4 = np.dtype([*OPEN_DTYPE_V3.descr, ("w2", "<f8"), ("hold", "<i8"), ("j6", "<f8", 6)])
OPEN_DTYPE_V5 = np.dtype([*OPEN_DTYPE_V4.descr, ("c1", "<f8")])
OPEN_DTYPE_V6 = np.dtype([*OPEN_DTYPE_V5.descr, ("t5", "<f8", 5)])
OPEN_DTYPE = np.dtype([*OPEN_DTYPE_V6.descr, ("k", "<f8", 28)])
OPEN_DTYPE_V1 = np.dtype(
    [("cluster", "<i8"), ("last", "<i8"), ("n", "<i8"), ("a6", "<f8", 6), ("b", "<f8", 3)]
)
OPEN_DTYPE_V2 = np.dtype([*OPEN_DTYPE_V1.descr, ("s2", "<f8")])
ROW_FIELDS_V2 = ("anchor", "x_ref", "a6", "j6", "b", "saa", "sab", "sbb", "n_obs", "n_closed")
ROW_FIELDS_V4 = (*ROW_FIELDS_V2, "w1", "w2")
ROW_FIELDS_V5 = (*ROW_FIELDS_V4, "c1")
ROW_FIELDS = (*ROW_FIELDS_V5, "q2")
"""The row record's fields that are ``LandmarkSums`` arrays of the same name (``_`` +
field); ``n_open`` is derived from the open-pass records."""


@dataclass(frozen=True)
class Layout:
    """One pack version: its row record, the row fields it stores, its open-pass record."""

    version: int
    row: np.dtype
    fields: tuple[str, ...]
    open: np.dtype


_LAYOUTS = {
    PACK_VERSION: Layout(PACK_VERSION, ROW_DTYPE, ROW_FIELDS, OPEN_DTYPE),
    6: Layout(6, ROW_DTYPE_V5, ROW_FIELDS_V5, OPEN_DTYPE_V6),
    5: Layout(5, ROW_DTYPE_V5, ROW_FIELDS_V5, OPEN_DTYPE_V5),
    4: Layout(4, ROW_DTYPE_V4, ROW_FIELDS_V4, OPEN_DTYPE_V4),
    3: Layout(3, ROW_DTYPE_V4, ROW_FIELDS_V4, OPEN_DTYPE_V3),
    2: Layout(2, ROW_DTYPE_V2, ROW_FIELDS_V2, OPEN_DTYPE_V2),
    1: Layout(1, ROW_DTYPE_V2, ROW_FIELDS_V2, OPEN_DTYPE_V1),
}


def layout(version: int) -> Layout:
    """The layout of pack ``version``; ``ValueError`` for an unknown one.

    >>> layout(3).row is ROW_DTYPE_V4, layout(3).open is OPEN_DTYPE_V3
    (True, True)
    """
    try:
        return _LAYOUTS[version]
    except (KeyError, TypeError):
        raise ValueError("unknown landmark state version") from None


def encode(lay: Layout, rec: np.ndarray | np.void, op: np.ndarray) -> bytes:
    """The blob: version byte, row record ``rec`` (of ``lay.row``), open records ``op``
    (of ``lay.open``)."""
    return bytes([lay.version]) + rec.tobytes() + op.tobytes()


def decode(blob: bytes) -> tuple[Layout, np.void, np.ndarray]:
    """A blob's layout, row record and ``n_open`` open-pass records (read-only views of
    ``blob``). ``ValueError`` for an empty blob, an unknown version, a negative ``n_open``
    or too few bytes."""
    if not blob:
        raise ValueError("unknown landmark state version")
    lay = layout(blob[0])
    rec = np.frombuffer(blob, lay.row, count=1, offset=1)[0]
    n_open = int(rec["n_open"])
    if n_open < 0:
        raise ValueError(f"landmark state: n_open {n_open} < 0")
    op = np.frombuffer(blob, lay.open, count=n_open, offset=1 + lay.row.itemsize)
    return lay, rec, op


def pack_rows(sums: Any, rows: NDArray[np.int64]) -> list[bytes]:
    """Rows of a :class:`~hdmap.mapping.estimator.sums.LandmarkSums` (checked) as blobs.

    A row without any pull (``EstimatorConfig.extra_sigma_pos_m`` unset) is written in
    version 4, without the pull columns: 8 bytes less per row and per open pass, which
    keeps two rows with 8 open passes in one SQLite page; without range scale sums in
    version 5 or 6, with box-noise sums in :data:`PACK_VERSION`. Open passes by activity,
    then cluster."""
    o = sums._open
    out = []
    for row in rows.tolist():
        mine = o.of_row(row)
        mine = mine[np.lexsort((o.cluster[mine], o.last[mine]))]
        pulled = bool(sums._c1[row] != 0 or np.any(o.c1[mine] != 0))
        scaled = bool(np.any(o.t5[mine] != 0))
        noisy = bool(np.any(sums._q2[row] != 0) or np.any(o.k[mine] != 0))
        lay = layout(PACK_VERSION if noisy else 6 if scaled else 5 if pulled else 4)
        rec = np.zeros((), lay.row)
        for f in lay.fields:
            rec[f] = getattr(sums, "_" + f)[row].reshape(rec[f].shape)
        rec["n_open"] = mine.size
        out.append(encode(lay, rec, o.records(mine, lay)))
    return out


def unpack_rows(sums: Any, rows: NDArray[np.int64], blobs: Sequence[bytes]) -> None:
    """Restore blobs of :func:`pack_rows` into rows of ``sums`` without open passes (older
    versions: the fields they lack at their neutral values)."""
    for row, blob in zip(rows.tolist(), blobs, strict=True):
        lay, rec, op = decode(blob)
        v = lay.version
        for f in lay.fields:
            target = getattr(sums, "_" + f)
            target[row] = np.asarray(rec[f]).reshape(target[row].shape)
        if v < 3:
            sums._w1[row] = sums._w2[row] = float(rec["n_obs"])
        if v < 5:
            sums._c1[row] = 0.0
        if v < 7:
            sums._q2[row] = 0.0
        sums._n_open[row] = 0
        for o in op:
            sums._open.load(sums._alloc_slot((row, int(o["cluster"]))), o, v)
            if v == 1 and sums.config.cluster_robust:
                sums._a6[row] -= o["a6"]
                sums._b[row] -= o["b"]
