"""Per-landmark incremental sums (struct of arrays) with pass-level partial sums.

One row per landmark. Closed state per row (float64 unless noted):

=========  ====  =============================================================
field      n     meaning (coordinates relative to the row's anchor)
=========  ====  =============================================================
anchor     3     fixed origin of the row's sums (its first position), tile ENU
x_ref      3     reference position for the weights (last published estimate)
A          6     sum over closed passes of ``W_p`` (symmetric), the pass-weighted sum
                 ``A_p`` of its (compensated) ray terms ``Q~_j``
J          6     sum of the predicted terms ``Q_ref,j`` (conditioning test)
b          3     sum over closed passes of ``b~_p``, from ``b_p = sum Q~_j a_j`` (with
                 the weight correction)
S_AA       21    sum over closed passes of ``alpha_p alpha_p^T`` (symmetric 6x6;
                 ``alpha_p`` = ``W_p`` as a 6-vector)
S_Ab       18    sum over closed passes of ``alpha_p b~_p^T``
S_bb       6     sum over closed passes of ``b~_p b~_p^T``
n_obs      1     rays (int64)
n_closed   1     closed passes (int64)
n_open     1     open passes (int64, derived from the open-pass table)
w1, w2     2     sums of the rays' weights and of their squares (``Rays.weight``: a
                 vehicle's trust; they scale the model floor of the covariance)
c1         1     sum over closed passes of their pull ``tr C_p`` (the rays'
                 :func:`~hdmap.mapping.estimator.model.pull_terms`, scaled like ``A_p`` by the
                 pass weighting; 0 unless ``EstimatorConfig.extra_sigma_pos_m`` is set)
q2         2     closed passes' box-noise residual sum and degrees of freedom (inverse-range
                 form only, :mod:`hdmap.mapping.estimator.box_noise`)
=========  ====  =============================================================

so 71 float64 + 3 int64 = 592 bytes per landmark (:attr:`LandmarkSums.bytes_per_landmark`;
packed by :meth:`pack_rows`: the byte layout and its sizes are in
:mod:`hdmap.mapping.estimator.packing`).

Open passes: rays of one pass may arrive split over several :meth:`accumulate` calls,
interleaved with other passes, so each open (landmark, pass) keeps its partial sums in the
open-pass table (:mod:`hdmap.mapping.estimator.open_passes`: 440 bytes a pass, the
random-effects weighting a pass gets when it closes, the eviction rule). :meth:`solve`
includes the open passes weighted the same way, so a result never depends on when a pass
is closed. Callers close passes they know are over with :meth:`close_passes`.

>>> import numpy as np
>>> from hdmap.mapping.estimator.model import Rays
>>> s = LandmarkSums(capacity=2)
>>> rows = s.new_rows(1, np.array([[0.0, 20.0, 2.0]]))
>>> rows.tolist(), s.bytes_per_landmark, len(s.pack_rows(rows)[0])
([0], 592, 565)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping.estimator import packing, row_merge
from hdmap.mapping.estimator.box_noise import COMP, noise_ratio
from hdmap.mapping.estimator.model import (
    EstimatorConfig,
    Rays,
    effective_sigmas,
    mat_to_sym,
    outer6_to_tri,
    predicted_information,
    pull_terms,
    weights,
)
from hdmap.mapping.estimator.open_passes import OpenPasses, RayTerms
from hdmap.mapping.estimator.solve import Solution, solve_sums
from hdmap.mapping.estimator.terms import inverse_of, noise_terms, ray_terms, scale_terms

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_ROW_ARRAYS = ("_anchor", "_x_ref", "_a6", "_j6", "_b", "_saa", "_sab", "_sbb")
_ROW_ARRAYS += ("_n_obs", "_n_closed", "_n_open", "_w1", "_w2", "_c1", "_q2")
"""The per-row arrays of :class:`LandmarkSums`, grown together: the closed state."""


def _scatter_add(target: np.ndarray, idx: IntArray, values: np.ndarray) -> None:
    """``target[idx] += values`` with repeated indices summed (sort + reduceat)."""
    if idx.size == 0:
        return
    order = np.argsort(idx, kind="stable")
    s = idx[order]
    starts = np.flatnonzero(np.concatenate(([True], s[1:] != s[:-1])))
    target[s[starts]] += np.add.reduceat(values[order], starts, axis=0)


class LandmarkSums:
    """Incremental estimator state for many landmarks (one row each).

    Rows grow by capacity doubling; :meth:`accumulate` is vectorised over a batch of rays of
    many landmarks and passes, mixed and unsorted, at O(1) state per ray.
    """

    ROW_ARRAYS = _ROW_ARRAYS

    def __init__(self, config: EstimatorConfig | None = None, capacity: int = 1024):
        self.config = config or EstimatorConfig()
        self._n = 0
        cap = max(int(capacity), 1)
        self._anchor = np.zeros((cap, 3))
        self._x_ref = np.zeros((cap, 3))
        self._a6 = np.zeros((cap, 6))
        self._j6 = np.zeros((cap, 6))
        self._b = np.zeros((cap, 3))
        self._saa = np.zeros((cap, 21))
        self._sab = np.zeros((cap, 6, 3))
        self._sbb = np.zeros((cap, 6))
        self._n_obs = np.zeros(cap, np.int64)
        self._n_closed = np.zeros(cap, np.int64)
        self._n_open = np.zeros(cap, np.int64)
        self._w1 = np.zeros(cap)  # sum of the rays' weights (Rays.weight, default 1)
        self._w2 = np.zeros(cap)  # sum of their squares (the model floor's scale)
        self._c1 = np.zeros(cap)  # closed passes' pull (model.pull_terms, pass-weighted)
        self._q2 = np.zeros((cap, 2))  # closed passes' box-noise residuals, dof (box_noise)
        self._open = OpenPasses(noise=self._inverse)  # the open (landmark, pass) sums

    # ------------------------------------------------------------------ sizes
    def __len__(self) -> int:
        return self._n

    @property
    def bytes_per_landmark(self) -> int:
        """In-memory closed state per landmark, bytes (each open pass adds
        ``open_pass_bytes``)."""
        return int(sum(getattr(self, n)[0].nbytes for n in _ROW_ARRAYS))

    @property
    def open_pass_bytes(self) -> int:
        """Bytes of numeric state per open pass: its packed record with every sum this
        configuration keeps (version 7 in the inverse-range form, else 6; plus the row)."""
        return packing.layout(packing.PACK_VERSION if self._inverse else 6).open.itemsize

    @property
    def n_open_passes(self) -> int:
        return len(self._open)

    def open_clusters(self, row: int) -> list[int]:
        """Cluster ids of ``row``'s open passes."""
        return self._open.clusters(row)

    def open_passes(self) -> list[tuple[int, int]]:
        """The open (row, cluster) pairs, sorted.

        >>> s = LandmarkSums(capacity=1)
        >>> s.open_passes()
        []
        """
        return self._open.keys()

    def n_obs(self, rows: ArrayLike) -> IntArray:
        """Rays summed into each row."""
        return self._n_obs[np.asarray(rows, np.int64)].copy()

    def n_passes(self, rows: ArrayLike) -> IntArray:
        """Passes (clusters, closed and open) summed into each row."""
        r = np.asarray(rows, np.int64)
        return self._n_closed[r] + self._n_open[r]

    def anchor(self, rows: ArrayLike) -> Array:
        return self._anchor[np.asarray(rows, np.int64)].copy()

    def reference(self, rows: ArrayLike) -> Array:
        """Reference positions used for the weights, tile ENU."""
        r = np.asarray(rows, np.int64)
        return self._x_ref[r] + self._anchor[r]

    def set_reference(self, rows: ArrayLike, x: ArrayLike) -> None:
        """Override the reference positions (e.g. from a better initialiser)."""
        r = np.asarray(rows, np.int64)
        self._x_ref[r] = np.asarray(x, float) - self._anchor[r]

    # ------------------------------------------------------------------ rows
    def _grow(self, need: int) -> None:
        cap = self._anchor.shape[0]
        if need <= cap:
            return
        new = cap
        while new < need:
            new *= 2
        for name in _ROW_ARRAYS:
            old = getattr(self, name)
            arr = np.zeros((new, *old.shape[1:]), old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def new_rows(self, k: int, x0: ArrayLike) -> IntArray:
        """Append ``k`` landmarks at initial positions ``x0`` (k, 3); returns their rows."""
        x0 = np.asarray(x0, float).reshape(k, 3)
        if not np.isfinite(x0).all():
            raise ValueError("x0 must be finite")
        self._grow(self._n + k)
        rows = np.arange(self._n, self._n + k, dtype=np.int64)
        self._anchor[rows] = x0
        self._x_ref[rows] = 0.0
        self._n += k
        return rows

    def compact(self, keep: ArrayLike) -> IntArray:
        """Keep only rows ``keep``, renumbered 0.. in ascending order of their old numbers
        (every other row's sums and open passes go; capacity shrinks to twice what is
        kept). Returns each old row's new number (-1: gone). Rows are never reused, so the
        rows of retired and merged landmarks pile up until compacted; an ascending
        renumbering keeps every result bit for bit (sums are per row and open passes are
        ordered by (row, cluster), :meth:`OpenPasses.canonical`)."""
        keep = np.unique(self._check_rows(keep))
        new_of = np.full(self._n, -1, np.int64)
        new_of[keep] = np.arange(keep.size)
        cap = max(2 * keep.size, 16)
        for name in _ROW_ARRAYS:
            old = getattr(self, name)
            arr = np.zeros((cap, *old.shape[1:]), old.dtype)
            arr[: keep.size] = old[keep]
            setattr(self, name, arr)
        self._n = int(keep.size)
        self._open.renumber(new_of)
        return new_of

    def _check_rows(self, rows: ArrayLike) -> IntArray:
        r = np.asarray(rows, np.int64).reshape(-1)
        if r.size and (r.min() < 0 or r.max() >= self._n):
            raise IndexError("row out of range")
        return r

    # ------------------------------------------------------------------ open passes
    def _alloc_slot(self, key: tuple[int, int]) -> int:
        s = self._open.alloc(key)
        self._n_open[key[0]] += 1
        return s

    def _close_slots(self, slots: IntArray) -> None:
        if slots.size == 0:
            return
        self._fold_slots(slots)
        _scatter_add(self._n_open, self._open.row[slots], -np.ones(slots.size, np.int64))
        self._open.release(slots)

    def _fold_slots(self, slots: IntArray) -> None:
        """Add open passes' weighted sums to their rows' closed sums (the slots are then
        released by the caller)."""
        rows = self._open.row[slots]
        ratio = None
        if self._inverse:  # pooled with the closing passes, which then join the pool
            uniq, pos = np.unique(rows, return_inverse=True)
            ratio = self._pooled_ratio(uniq, slots, pos)[pos]
            _scatter_add(self._q2, rows, np.stack(self._open.residuals(slots), axis=1))
        a6, b, c1 = self._open.weighted(slots, self.config, ratio)
        self._add_closed(rows, a6, b, c1, _scatter_add)

    def _add_closed(self, rows: IntArray, a6: Array, b: Array, c1: Array | None, add) -> None:
        """Closed passes (or, without pass-level sums, rays) with terms ``a6``, ``b`` and
        pull ``c1`` into their rows' closed sums, summed by ``add``: ``_scatter_add`` or
        the unbuffered ``np.add.at`` (one by one, in order)."""
        if c1 is not None:
            add(self._c1, rows, c1)
        add(self._a6, rows, a6)
        add(self._b, rows, b)
        add(self._saa, rows, outer6_to_tri(a6))
        add(self._sab, rows, a6[:, :, None] * b[:, None, :])
        add(self._sbb, rows, mat_to_sym(b[:, :, None] * b[:, None, :]))
        add(self._n_closed, rows, np.ones(rows.size, np.int64))

    @property
    def _inverse(self) -> bool:
        return self.config.box_range and self.config.range_scale == "inverse"

    def box_noise_ratio(self, rows: ArrayLike) -> Array:
        """Per row the measured ratio of its boxes' inverse-range noise variance to the
        vehicles' claim, open passes included (:mod:`~hdmap.mapping.estimator.box_noise`;
        1 where nothing is measured yet)."""
        uniq, inv = np.unique(self._check_rows(rows), return_inverse=True)
        slots = self._open.of_rows(uniq)
        return self._pooled_ratio(uniq, slots, np.searchsorted(uniq, self._open.row[slots]))[inv]

    def _pooled_ratio(self, uniq: IntArray, slots: IntArray, pos: IntArray) -> Array:
        """Box-noise ratios of rows ``uniq`` with their open ``slots`` (at ``pos``) pooled."""
        q2 = self._q2[uniq].copy()
        _scatter_add(q2, pos, np.stack(self._open.residuals(slots), axis=1))
        return noise_ratio(q2[:, 0], q2[:, 1], self.config.range_noise_prior_dof)

    def close_passes(self, rows: ArrayLike | None = None, clusters: ArrayLike | None = None) -> int:
        """Close open passes: all (no arguments), those of ``rows``, those with a cluster id
        in ``clusters`` (every landmark), or the pairs ``(rows[i], clusters[i])`` (both);
        held passes stay open. Returns how many were closed."""
        slots = self._open.closable(rows, clusters)
        self._close_slots(slots)
        return int(slots.size)

    def _evict(self, rows: IntArray) -> None:
        """Close the least recently active passes of ``rows`` (unique, ascending) above
        ``max_open_passes`` (:meth:`OpenPasses.least_active`), in one vectorised call (the
        same sums, in the same order, as closing row by row)."""
        over = rows[self._n_open[rows] > self.config.max_open_passes]
        if over.size == 0:
            return
        self._close_slots(self._open.least_active(over, self.config.max_open_passes))

    # ------------------------------------------------------------------ held passes
    def release(self, hold: int, weight: float) -> IntArray:
        """Let ``hold``'s held passes go, their rays re-weighted to ``weight`` (exactly as if
        they had come with it: every ray term is linear in its weight); they become
        ordinary open passes. Returns the rows that had some.

        >>> import numpy as np
        >>> from hdmap.mapping.estimator.model import Rays
        >>> s = LandmarkSums(capacity=1)
        >>> row = s.new_rows(1, np.zeros((1, 3)))
        >>> from dataclasses import replace
        >>> r = Rays.from_angles(np.zeros((2, 3)), [0.1, 0.2], [0.1, 0.1], 0.01, 0.01, 1.0, 1.0)
        >>> rays = replace(r, weight=np.full(2, 0.05))
        >>> s.accumulate([0, 0], [11, 11], rays, hold=[7, 7])
        >>> s.n_held(), s.release(7, 1.0).tolist(), s.n_held(), s.release(7, 1.0).tolist()
        (1, [0], 0, [])
        """
        o = self._open
        slots = o.held(hold)
        rows = o.row[slots]
        if slots.size == 0:
            return rows
        n = np.maximum(o.n[slots], 1)
        f = float(weight) / np.maximum(o.w[slots] / n, 1e-300)
        o.a6[slots] *= f[:, None]
        o.b[slots] *= f[:, None]
        o.t5[slots] *= f[:, None]
        o.k[slots, COMP] *= f[:, None]  # the fit's weights are the claim's, not the trust's
        _scatter_add(self._j6, rows, f[:, None] * o.j6[slots])
        o.c1[slots] *= f  # linear in the rays' weight, like A_p
        _scatter_add(self._w1, rows, (f - 1.0) * o.w[slots])
        _scatter_add(self._w2, rows, (f**2 - 1.0) * o.w2[slots])
        o.w[slots] *= f
        o.w2[slots] *= f**2
        o.j6[slots] = 0.0
        o.hold[slots] = 0
        rows = np.unique(rows)
        self._evict(rows)
        return rows

    def drop_held(self, hold: int) -> IntArray:
        """Take ``hold``'s held passes out, as if their rays had never been added. Returns
        the rows that had some."""
        o = self._open
        slots = o.held(hold)
        rows = o.row[slots]
        if slots.size == 0:
            return rows
        _scatter_add(self._n_obs, rows, -o.n[slots])
        _scatter_add(self._w1, rows, -o.w[slots])
        _scatter_add(self._w2, rows, -o.w2[slots])
        _scatter_add(self._n_open, rows, -np.ones(slots.size, np.int64))
        o.release(slots)
        return np.unique(rows)

    def n_held(self, rows: ArrayLike | None = None) -> int:
        """Held passes (of ``rows``, default all)."""
        o = self._open
        slots = o.all_slots() if rows is None else o.of_rows(np.asarray(rows))
        return int(np.count_nonzero(o.hold[slots]))

    # ------------------------------------------------------------------ accumulate
    def accumulate(
        self, rows: ArrayLike, clusters: ArrayLike, rays: Rays, hold: ArrayLike | None = None
    ) -> None:
        """Add rays (``rows[j]`` is ray j's landmark, ``clusters[j]`` its pass key).

        Weights use each row's reference position as it is before this call. ``hold[j]``
        (default 0: none) puts ray j's pass *on hold* for the holder with that key (a
        vehicle on probation): the pass stays open and separate, counts in :meth:`solve`
        with the weight its rays have, and is later either re-weighted and let go
        (:meth:`release`) or taken out as if never added (:meth:`drop_held`). A cluster is
        held or not for good: use distinct cluster keys for a pass's held rays.

        Invariant: the state after a list of rays is the same, to the bit, however the list
        is cut into calls (docs/estimator.md section 5): rays go in one by one in order,
        and a pass closed on the way (:meth:`OpenPasses.assign`) holds the rays before it.
        """
        r = self._check_rows(rows)
        n = r.size
        if len(rays) != n:
            raise ValueError("rows and rays differ in length")
        if n == 0:
            return
        c = np.asarray(clusters, np.int64).reshape(-1)
        if c.size != n:
            raise ValueError("clusters and rays differ in length")
        hk = np.zeros(n, np.int64) if hold is None else np.asarray(hold, np.int64).reshape(-1)
        if hk.size != n:
            raise ValueError("hold and rays differ in length")
        held = hk != 0
        if held.any() and not self.config.cluster_robust:
            raise ValueError("held passes need pass-level sums (cluster_robust)")
        origin_rel = np.asarray(rays.origin, float) - self._anchor[r]
        x_ref = self._x_ref[r]
        inv = inverse_of(rays, origin_rel, x_ref, self.config)  # once for the three below
        wts = weights(rays, origin_rel, x_ref, self.config)  # once for the two that weigh
        alpha, beta = ray_terms(rays, origin_rel, x_ref, self.config, inv, wts)
        t5 = scale_terms(rays, origin_rel, self.config, x_ref, inv)
        kn = noise_terms(rays, origin_rel, x_ref, self.config, inv)
        j6 = predicted_information(rays, origin_rel, x_ref, self.config, wts)
        # the pull sum of an unreported pass bias: only when configured (zeros otherwise)
        pulled = self.config.extra_sigma_pos_m > 0
        pull = pull_terms(rays, origin_rel, self._x_ref[r], self.config) if pulled else None
        if not (np.isfinite(alpha).all() and np.isfinite(beta).all()):
            raise ValueError("non-finite ray terms (check directions and sigmas)")
        wr = rays.weights_or_ones()
        if not self.config.cluster_robust:
            if t5 is not None:
                raise ValueError("per-pass range scales need pass-level sums (cluster_robust)")
            np.add.at(self._n_obs, r, 1)
            np.add.at(self._w1, r, wr)
            np.add.at(self._w2, r, wr**2)
            np.add.at(self._j6, r, j6)
            self._add_closed(r, alpha, beta, pull, np.add.at)  # every ray its own "pass"
            return
        o = self._open
        o.check_holds(r, c, hk)
        slots, stamps, closes = o.assign(
            r, c, hk, self._n_obs, self._n_open, self.config.max_open_passes
        )
        s_az, s_el = effective_sigmas(rays, self.config)
        var = np.broadcast_to(0.5 * (s_az**2 + s_el**2), (n,))
        terms = RayTerms(j6, alpha, beta, t5, kn, pull, var, wr)

        def add(lo: int, hi: int) -> None:
            """Rays ``lo:hi`` into their rows and passes, one by one in order."""
            rs, h, w = r[lo:hi], held[lo:hi], wr[lo:hi]
            np.add.at(self._n_obs, rs, 1)
            np.add.at(self._w1, rs, w)
            np.add.at(self._w2, rs, w**2)
            np.add.at(self._j6, rs[~h], j6[lo:hi][~h])
            o.add_rays(slots[lo:hi], h, terms.rows(lo, hi), stamps[lo:hi])

        if not self._inverse:
            # a pass's weighting depends on its own sums only: the rays first, then the
            # passes closed on the way (each holds exactly the rays before its closing)
            add(0, n)
            self._close_many([slot for _at, slot in closes])
            return
        done = 0  # inverse form: a closing pools the row's other open passes as they are
        for at, slot in closes:
            add(done, at)
            done = at
            self._close_detached(slot)
        add(done, n)

    def accumulate_parts(
        self, parts: Sequence[tuple[ArrayLike, ArrayLike, Rays, ArrayLike]]
    ) -> None:
        """:meth:`accumulate` of ``(rows, clusters, rays, hold)`` parts, in order, in one
        call (the same state as one call per part: the invariant above)."""
        if not parts:
            return
        self.accumulate(
            np.concatenate([np.asarray(p[0], np.int64).reshape(-1) for p in parts]),
            np.concatenate([np.asarray(p[1], np.int64).reshape(-1) for p in parts]),
            Rays.concat([p[2] for p in parts]),
            np.concatenate([np.asarray(p[3], np.int64).reshape(-1) for p in parts]),
        )

    def _close_many(self, slots: list[int]) -> None:
        """:meth:`_close_detached` of each slot, in order. Slots of distinct rows are folded
        in one call: each row then gets exactly one slot's terms, added as alone (a pass's
        weighting is its own: the same bits), and the slots go on the free list in the same
        order; two slots of one row are folded one by one (their sum's order would differ)."""
        if len(slots) > 1:
            arr = np.array(slots, np.int64)
            rows = self._open.row[arr]
            if np.unique(rows).size == rows.size:
                self._fold_slots(arr)
                self._open.free_slots(arr)
                return
        for slot in slots:
            self._close_detached(slot)

    def _close_detached(self, slot: int) -> None:
        """Fold a slot :meth:`OpenPasses.assign` detached and free it."""
        one = np.array([slot], np.int64)
        self._fold_slots(one)
        self._open.free_slots(one)

    # ------------------------------------------------------------------ solve
    def solve(self, rows: ArrayLike, update_reference: bool = True) -> Solution:
        """Estimate and covariance of ``rows`` (open passes included).

        With ``update_reference``, rows whose solution is ``ok`` take it as the reference
        position for the weights of their future rays (part of the state: the same calls
        give the same results after :meth:`pack_rows` / :meth:`unpack_rows`).
        """
        r = self._check_rows(rows)
        uniq, inv = np.unique(r, return_inverse=True)
        saa, sab, sbb = self._saa[uniq].copy(), self._sab[uniq].copy(), self._sbb[uniq].copy()
        a_all, b_all = self._a6[uniq].copy(), self._b[uniq].copy()
        n_cl = self._n_closed[uniq] + self._n_open[uniq]
        j6 = self._j6[uniq].copy()
        c1 = self._c1[uniq].copy()
        o = self._open
        slots = o.of_rows(uniq)
        if slots.size:
            pos = np.searchsorted(uniq, o.row[slots])
            _scatter_add(j6, pos, o.j6[slots])
            ratio = self._pooled_ratio(uniq, slots, pos)[pos] if self._inverse else None
            a6, b, c1o = o.weighted(slots, self.config, ratio)
            _scatter_add(c1, pos, c1o)
            _scatter_add(a_all, pos, a6)
            _scatter_add(b_all, pos, b)
            _scatter_add(saa, pos, outer6_to_tri(a6))
            _scatter_add(sab, pos, a6[:, :, None] * b[:, None, :])
            _scatter_add(sbb, pos, mat_to_sym(b[:, :, None] * b[:, None, :]))
        sol = solve_sums(
            a_all,
            b_all,
            saa,
            sab,
            sbb,
            self._n_obs[uniq],
            n_cl,
            self.config,
            j6,
            floor_scale=np.divide(
                self._w2[uniq], self._w1[uniq], out=np.ones(uniq.size), where=self._w1[uniq] > 0
            ),
            pull=c1 if c1.any() else None,
        )
        if update_reference:
            ok = sol.ok
            self._x_ref[uniq[ok]] = sol.x[ok]
        anchor = self._anchor[uniq]
        out = replace(sol, x=sol.x + anchor, x_raw=sol.x_raw + anchor)
        if uniq.size == r.size and np.array_equal(uniq, r):
            return out
        return Solution(**{k: v[inv] for k, v in out.__dict__.items()})

    # ------------------------------------------------------------------ merge
    def merge_rows(
        self,
        dst: int,
        src: int,
        rotation: ArrayLike | None = None,
        translation: ArrayLike | None = None,
    ) -> None:
        """Fold row ``src`` into row ``dst`` (two landmarks found to be one); ``src`` is
        left empty.

        ``rotation`` R and ``translation`` t map ``src``'s frame to ``dst``'s (``x_dst = R
        x_src + t``; default: the same frame); every ray term moves exactly
        (:class:`~hdmap.mapping.estimator.frame_change.FrameChange`;
        :func:`hdmap.mapping.estimator.row_merge.merge_rows`).

        An open pass of ``src`` joins ``dst``'s open pass of the same cluster (one pass
        that saw "both" landmarks is one cluster again) or becomes a new open pass. The
        rays keep the weights they got from their own row's reference; with the same
        reference and a rotation about the vertical (the compensation is defined in az/el
        about the local up), the result equals one row fed every ray.
        """
        row_merge.merge_rows(self, dst, src, rotation, translation)

    # ------------------------------------------------------------------ persistence
    def pack_rows(self, rows: ArrayLike) -> list[bytes]:
        """Serialise rows (closed sums, reference, open passes) to self-contained blobs
        (:func:`hdmap.mapping.estimator.packing.pack_rows`)."""
        return packing.pack_rows(self, self._check_rows(rows))

    def unpack_rows(self, blobs: Sequence[bytes], rows: ArrayLike | None = None) -> IntArray:
        """Restore packed rows into new rows (default) or over ``rows`` (their open passes
        are dropped first). Returns the rows."""
        if rows is None:
            r = self.new_rows(len(blobs), np.zeros((len(blobs), 3)))
        else:
            r = self._check_rows(rows)
            if r.size != len(blobs):
                raise ValueError("rows and blobs differ in length")
            self._open.release(self._open.of_rows(r))
        packing.unpack_rows(self, r, blobs)
        return r
