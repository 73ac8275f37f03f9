"""A row's sums seen from another row's frame: what
:meth:`~hdmap.mapping.estimator.sums.LandmarkSums.merge_rows` adds to the row it keeps.

``rotation`` R and ``translation`` t map the source row's frame to the destination's
(``x_dst = R x_src + t``). Every ray term moves exactly: ``A_j -> R A_j R^T`` (a linear
map T of the 6-vector) and, with ``d = R anchor_src + t - anchor_dst``, ``b_j -> R b_j +
A'_j d = R b_j + L(d) alpha'_j``, so per pass ``alpha' = T alpha``, ``b' = R b + L
alpha'`` and the sandwich sums follow:

    S_AA' = T S_AA T^T,   S_Ab' = T S_Ab R^T + S_AA' L^T,
    S_bb' = R S_bb R^T + R S_Ab^T T^T L^T + L T S_Ab R^T + L S_AA' L^T.

Traces (the pull ``c1``) and counts are the same in every frame. An open pass's range
scale terms (:func:`~hdmap.mapping.estimator.terms.scale_terms`) move as ``A_xs' = R A_xs``,
``A_ss' = A_ss``, ``b_s' = b_s + A_xs' . d``.

>>> f = FrameChange.between(np.zeros(3), np.zeros(3))
>>> a6, b = f.terms(np.array([1.0, 2, 3, 0, 0, 0]), np.array([1.0, 0, 0]))
>>> a6.tolist(), b.tolist()
([1.0, 2.0, 3.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping.estimator.model import (
    SYM_BASIS,
    TRI6_I,
    TRI6_J,
    apply_matrix,
    mat_to_sym,
    sym_to_mat,
    tri_to_mat6,
)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FrameChange:
    """The maps of one frame change: ``r`` (R, 3x3), ``t6`` (T, 6x6, ``A -> R A R^T`` on
    the 6-vector) and ``lm`` (L(d), 3x6, ``A d`` for the 6-vector of ``A``)."""

    r: Array
    t6: Array
    lm: Array
    d: Array

    @classmethod
    def between(
        cls,
        anchor_src: Array,
        anchor_dst: Array,
        rotation: ArrayLike | None = None,
        translation: ArrayLike | None = None,
    ) -> FrameChange:
        """From the source row's frame (anchored at ``anchor_src``) to the destination's;
        default rotation and translation: the same frame."""
        r = np.eye(3) if rotation is None else np.asarray(rotation, float).reshape(3, 3)
        t = np.zeros(3) if translation is None else np.asarray(translation, float).reshape(3)
        t6 = np.stack([mat_to_sym(r @ SYM_BASIS[k] @ r.T) for k in range(6)], axis=1)
        d = r @ anchor_src + t - anchor_dst
        return cls(r, t6, apply_matrix(d), d)

    def terms(self, a6: Array, b: Array) -> tuple[Array, Array]:
        """A pass's (or a row's) ``alpha``, ``b`` in the destination frame."""
        a6n = a6 @ self.t6.T
        return a6n, b @ self.r.T + a6n @ self.lm.T

    def scale(self, t5: Array) -> Array:
        """An open pass's range scale terms ``(A_xs, A_ss, b_s)`` (..., 5) in the
        destination frame."""
        out = np.array(t5, float, copy=True)
        out[..., :3] = t5[..., :3] @ self.r.T
        out[..., 4] = t5[..., 4] + out[..., :3] @ self.d
        return out

    def information(self, j6: Array) -> Array:
        """A predicted information ``J`` (a 6-vector) in the destination frame."""
        return j6 @ self.t6.T

    def sandwich(self, saa: Array, sab: Array, sbb: Array) -> tuple[Array, Array, Array]:
        """The sandwich sums ``S_AA`` (21, upper triangle), ``S_Ab`` (6x3) and ``S_bb``
        (6) in the destination frame, in the same layouts."""
        t6, r, lm = self.t6, self.r, self.lm
        saa_m = t6 @ tri_to_mat6(saa) @ t6.T
        t_sab_r = t6 @ sab @ r.T
        cross = lm @ t_sab_r
        sbb_m = r @ sym_to_mat(sbb) @ r.T + cross + cross.T + lm @ saa_m @ lm.T
        return saa_m[TRI6_I, TRI6_J], t_sab_r + saa_m @ lm.T, mat_to_sym(sbb_m)
