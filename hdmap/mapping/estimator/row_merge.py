"""Two rows of :class:`~hdmap.mapping.estimator.sums.LandmarkSums` folded into one (two
landmarks found to be one sign): every term moved into the kept row's frame
(:class:`~hdmap.mapping.estimator.frame_change.FrameChange`), the open passes joined by
cluster. Reads and writes the sums' arrays (as :mod:`hdmap.mapping.estimator.packing`
does); no I/O.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from hdmap.mapping.estimator.box_noise import in_frame
from hdmap.mapping.estimator.frame_change import FrameChange

if TYPE_CHECKING:
    from hdmap.mapping.estimator.sums import LandmarkSums


def merge_rows(
    sums: LandmarkSums,
    dst: int,
    src: int,
    rotation: ArrayLike | None = None,
    translation: ArrayLike | None = None,
) -> None:
    """:meth:`LandmarkSums.merge_rows <hdmap.mapping.estimator.sums.LandmarkSums.merge_rows>`."""
    if dst == src:
        raise ValueError("cannot merge a row into itself")
    d_row, s_row = sums._check_rows([dst, src]).tolist()
    frame = FrameChange.between(sums._anchor[s_row], sums._anchor[d_row], rotation, translation)
    a6, b = frame.terms(sums._a6[s_row], sums._b[s_row])
    sums._a6[d_row] += a6
    sums._b[d_row] += b
    sums._j6[d_row] += frame.information(sums._j6[s_row])
    sums._c1[d_row] += sums._c1[s_row]  # a trace: the same in every frame
    sums._q2[d_row] += sums._q2[s_row]  # scalars: the same in every frame
    saa, sab, sbb = frame.sandwich(sums._saa[s_row], sums._sab[s_row], sums._sbb[s_row])
    sums._saa[d_row] += saa
    sums._sab[d_row] += sab
    sums._sbb[d_row] += sbb
    sums._n_obs[d_row] += sums._n_obs[s_row]
    sums._w1[d_row] += sums._w1[s_row]
    sums._w2[d_row] += sums._w2[s_row]
    sums._n_closed[d_row] += sums._n_closed[s_row]
    o = sums._open
    mine = o.of_row(s_row)
    for sl in mine.tolist():
        a6o, bo = frame.terms(o.a6[sl], o.b[sl])
        key = (d_row, int(o.cluster[sl]))
        to = o.slot.get(key)
        if to is None:
            to = sums._alloc_slot(key)
        o.fold(
            to,
            sl,
            a6o,
            bo,
            frame.information(o.j6[sl]),
            frame.scale(o.t5[sl]),
            in_frame(o.k[sl], frame),
        )
    o.release(mine)
    for name in sums.ROW_ARRAYS:
        getattr(sums, name)[s_row] = 0
    sums._evict(np.array([d_row], np.int64))
