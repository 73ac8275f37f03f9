"""The open passes of :class:`~hdmap.mapping.estimator.sums.LandmarkSums`: one slot per open
(landmark, pass) with the pass's partial sums.

Rays of one pass may arrive split over several ``accumulate`` calls, interleaved with
other passes, so each open (landmark, pass) keeps its partial ``A_p``, ``b_p`` (9 floats
+ cluster id, ray count, activity stamp, angular variance, ray weight sums c and c^2,
holder key, held ``J``, pull, range scale sums: 224 bytes, the size of its packed record
:data:`~hdmap.mapping.estimator.packing.OPEN_DTYPE`). A pass enters the row's ``A``, ``b``
and sandwich sums when it closes, with the random-effects weighting of
:func:`hdmap.mapping.estimator.model.pass_weighted` (``W_p = (I + A_p S)^-1 A_p``, ``S``
the configured ``pass_sigma_m`` squared: a pass brings at most ``S^-1`` of information,
however many rays it has): :meth:`OpenPasses.weighted`. ``solve`` includes the open passes
the same way, so a result never depends on when a pass is closed, unless a ray of an
already closed pass arrives, which then starts a new cluster (the covariance misses that
pass's cross term).

Eviction rule: a row keeps at most ``max_open_passes`` open; opening one more closes the
least recently active (:meth:`OpenPasses.least_active`; the activity stamp is the row's
ray count at the pass's last ray, so the rule is deterministic and survives ``pack_rows``
/ ``unpack_rows``). A *held* pass (a holder key other than 0: a vehicle on probation) is
never closed, by eviction or by ``close_passes``, until its holder is settled.

Slots are recycled through a free list; the table grows by doubling.

>>> t = OpenPasses()
>>> t.alloc((0, 7)), t.alloc((0, 3)), t.alloc((1, 7))
(0, 1, 2)
>>> t.release(np.array([1])); t.keys(), t.clusters(0), t.alloc((2, 5))
([(0, 7), (1, 7)], [7], 1)
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping.estimator import box_noise
from hdmap.mapping.estimator.model import EstimatorConfig, pass_weighted
from hdmap.mapping.estimator.packing import PACK_VERSION, Layout
from hdmap.mapping.estimator.terms import eliminate_scale

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_ARRAYS = ("row", "cluster", "last", "n", "a6", "b", "s2", "w", "w2", "hold", "j6", "c1", "t5", "k")
"""The per-slot arrays of :class:`OpenPasses`, grown together."""


@dataclass(frozen=True)
class RayTerms:
    """What each ray adds to its open pass (rows follow the rays; None: not configured):
    predicted information ``j6`` (held passes keep it), ``alpha`` / ``beta`` (the raw
    ``A_p`` / ``b_p`` terms), range scale sums ``t5``, box-noise sums ``kn``, pull, angular
    variance ``var`` and weight ``w``."""

    j6: Array
    alpha: Array
    beta: Array
    t5: Array | None
    kn: Array | None
    pull: Array | None
    var: Array
    w: Array

    def rows(self, lo: int, hi: int) -> RayTerms:
        """The terms of rays ``lo:hi``."""
        cut = {f.name: getattr(self, f.name) for f in fields(self)}
        return RayTerms(**{k: None if v is None else v[lo:hi] for k, v in cut.items()})


class OpenPasses:
    """The open (landmark row, cluster) passes and their partial sums, one slot each.

    Per slot: ``row`` (-1: a free slot), ``cluster``, ``last`` (the activity stamp),
    ``n`` (rays), ``a6`` and ``b`` (the raw ``A_p`` and ``b_p``), ``s2`` (sum of the rays'
    angular variances), ``w`` and ``w2`` (sums of the rays' weights and of their squares),
    ``hold`` (the holder's key, 0: not held), ``j6`` (a held pass's predicted
    information), ``c1`` (the pass's raw pull,
    :func:`~hdmap.mapping.estimator.model.pull_terms`) and ``t5`` (its range scale sums,
    :func:`~hdmap.mapping.estimator.terms.scale_terms`) and ``k`` (in the inverse-range
    form its compensation and box-noise fit sums, :mod:`~hdmap.mapping.estimator.box_noise`).
    """

    def __init__(self, capacity: int = 16, noise: bool = False) -> None:
        """``noise``: keep the inverse-range form's box-noise sums ``k`` (else ``k`` has no
        columns: 224 bytes less per open pass)."""
        self.slot: dict[tuple[int, int], int] = {}
        """(row, cluster) -> its slot."""
        self.row_slots: dict[int, list[int]] = {}
        """row -> its open slots (any order)."""
        self.free: list[int] = []
        self.hi = 0
        """Slots ever used: every slot below is open or on the free list."""
        cap = max(int(capacity), 1)
        self.row = np.full(cap, -1, np.int64)
        self.cluster = np.zeros(cap, np.int64)
        self.last = np.zeros(cap, np.int64)
        self.n = np.zeros(cap, np.int64)
        self.a6 = np.zeros((cap, 6))
        self.b = np.zeros((cap, 3))
        self.s2 = np.zeros(cap)  # sum over the pass's rays of their angular variance
        self.w = np.zeros(cap)  # sum of the rays' weights (Rays.weight, default 1)
        self.w2 = np.zeros(cap)  # sum of their squares
        self.hold = np.zeros(cap, np.int64)  # held: the holder's key (0: not held)
        self.j6 = np.zeros((cap, 6))  # held passes' predicted information
        self.c1 = np.zeros(cap)  # the pass's pull (model.pull_terms), raw
        self.t5 = np.zeros((cap, 5))  # its range scale sums (model.scale_terms)
        # inverse form only: compensation, noise fit
        self.k = np.zeros((cap, box_noise.WIDTH if noise else 0))

    def __len__(self) -> int:
        return len(self.slot)

    def keys(self) -> list[tuple[int, int]]:
        """The open (row, cluster) pairs, sorted."""
        return sorted(self.slot)

    def clusters(self, row: int) -> list[int]:
        """Cluster ids of ``row``'s open passes, sorted."""
        return sorted(int(self.cluster[s]) for s in self.row_slots.get(int(row), ()))

    # ------------------------------------------------------------------ slots
    def alloc(self, key: tuple[int, int]) -> int:
        """A zeroed slot for the pass ``key`` (row, cluster), which must not be open."""
        if self.free:
            s = self.free.pop()
        else:
            s = self.hi
            self.hi += 1
            if s >= self.row.shape[0]:
                for name in _ARRAYS:
                    old = getattr(self, name)
                    arr = np.zeros((2 * old.shape[0], *old.shape[1:]), old.dtype)
                    arr[: old.shape[0]] = old
                    setattr(self, name, arr)
        self.slot[key] = s
        self.row_slots.setdefault(key[0], []).append(s)
        self.row[s], self.cluster[s] = key
        self.last[s] = self.n[s] = 0
        self.a6[s] = 0.0
        self.b[s] = 0.0
        self.s2[s] = 0.0
        self.w[s] = self.w2[s] = 0.0
        self.hold[s] = 0
        self.j6[s] = 0.0
        self.c1[s] = 0.0
        self.t5[s] = 0.0
        self.k[s] = 0.0
        return s

    def release(self, slots: IntArray) -> None:
        """Forget open slots (their sums already folded or dropped); free them in order."""
        for s in slots.tolist():
            self.detach(s)
        self.free_slots(slots)

    def detach(self, s: int) -> None:
        """Take slot ``s`` out of the open passes (its pass is no longer found by its key
        and a new ray of it opens another slot) but keep its sums until
        :meth:`free_slots` (a pass closed in the middle of an ``accumulate`` call is folded
        after the call's rays are added)."""
        row, cl = int(self.row[s]), int(self.cluster[s])
        del self.slot[(row, cl)]
        mine = self.row_slots[row]
        mine.remove(s)
        if not mine:
            del self.row_slots[row]

    def renumber(self, new_of: IntArray) -> None:
        """Rows renumbered (``new_of[old]``, -1: the row is gone with its open passes; the
        order of the rows kept must not change, :meth:`canonical` relies on it)."""
        live = np.flatnonzero(self.row[: self.hi] >= 0)
        self.release(self.canonical(live[new_of[self.row[live]] < 0]))
        live = np.flatnonzero(self.row[: self.hi] >= 0)
        self.row[live] = new_of[self.row[live]]
        self.slot = {(int(new_of[r]), c): s for (r, c), s in self.slot.items()}
        self.row_slots = {int(new_of[r]): mine for r, mine in self.row_slots.items()}

    def free_slots(self, slots: IntArray) -> None:
        """Put detached slots on the free list, in order."""
        for s in slots.tolist():
            self.row[s] = -1
            self.free.append(s)

    def canonical(self, slots: IntArray) -> IntArray:
        """``slots`` ordered by (row, cluster). Every list of slots here comes in this
        order, whatever slots the passes happen to occupy (that follows the order rays
        came in and the free list): what sums over a row's open passes is then the same
        after ``pack_rows`` / ``unpack_rows`` and however the rays were cut into calls."""
        slots = np.asarray(slots, np.int64)
        return slots[np.lexsort((self.cluster[slots], self.row[slots]))]

    # ------------------------------------------------------------------ rays in order
    def check_holds(self, r: IntArray, c: IntArray, hk: IntArray) -> None:
        """Refuse rays ``(row r, cluster c, holder hk)`` of one pass both held and not,
        within them or against an open pass (before anything changes)."""
        order = np.lexsort((c, r))
        rs, cs, hs = r[order], c[order], hk[order]
        starts = np.flatnonzero(np.r_[True, (rs[1:] != rs[:-1]) | (cs[1:] != cs[:-1])])
        if np.any(np.minimum.reduceat(hs, starts) != np.maximum.reduceat(hs, starts)):
            raise ValueError("rays of one (landmark, pass) both held and not")
        firsts = zip(rs[starts].tolist(), cs[starts].tolist(), hs[starts].tolist(), strict=True)
        for row, cl, h in firsts:
            s = self.slot.get((row, cl))
            if s is not None and int(self.hold[s]) != h:
                raise ValueError("rays of one (landmark, pass) both held and not")

    def assign(
        self, r: IntArray, c: IntArray, hk: IntArray, n_obs: IntArray, n_open: IntArray, keep: int
    ) -> tuple[IntArray, IntArray, list[tuple[int, int]]]:
        """Each ray's open pass, ray by ray in order: a ray of a pass not open opens one
        (``n_open`` of its row + 1), and a row with more than ``keep`` passes not held then
        closes its least recently active other one (by activity stamp, then cluster id;
        ``n_open`` - 1). Returns the slot and the activity stamp (its row's ray count,
        ``n_obs`` before the call, with it) of each ray, and the closings as (position of
        the ray that caused it, slot), in order; a closed slot is detached here and folded
        by the caller after the rays before it are added (:meth:`free_slots` then)."""
        n = r.size
        slots = np.empty(n, np.int64)
        stamps = np.empty(n, np.int64)
        closes: list[tuple[int, int]] = []
        count: dict[int, int] = {}
        recent: dict[int, int] = {}  # slot -> its stamp in this call so far
        for i, (row, cl, h) in enumerate(zip(r.tolist(), c.tolist(), hk.tolist(), strict=True)):
            k = count.get(row)
            k = int(n_obs[row]) + 1 if k is None else k + 1
            count[row] = k
            s = self.slot.get((row, cl))
            if s is None:
                s = self.alloc((row, cl))
                n_open[row] += 1
                self.hold[s] = h
                if h == 0:
                    others = [x for x in self.row_slots[row] if x != s and self.hold[x] == 0]
                    while len(others) >= keep and others:
                        victim = min(
                            others,
                            key=lambda x: (recent.get(x, int(self.last[x])), self.cluster[x]),
                        )
                        others.remove(victim)
                        self.detach(victim)
                        n_open[row] -= 1
                        closes.append((i, victim))
            slots[i] = s
            stamps[i] = k
            recent[s] = k
        return slots, stamps, closes

    def add_rays(
        self, ss: IntArray, held: NDArray[np.bool_], t: RayTerms, stamps: IntArray
    ) -> None:
        """Rays' terms ``t`` into their passes ``ss`` (:meth:`assign`), one by one in order
        (unbuffered ``np.add.at``: the sums do not depend on how rays are cut into calls);
        each pass's activity stamp becomes that of its last ray here (a stamp can go down:
        a dropped holder's rays leave the row's count)."""
        if held.any():
            np.add.at(self.j6, ss[held], t.j6[held])
        np.add.at(self.w2, ss, t.w**2)
        np.add.at(self.a6, ss, t.alpha)
        np.add.at(self.b, ss, t.beta)
        if t.t5 is not None:
            np.add.at(self.t5, ss, t.t5)
        if t.kn is not None:
            np.add.at(self.k, ss, t.kn)
        if t.pull is not None:
            np.add.at(self.c1, ss, t.pull)
        np.add.at(self.s2, ss, t.var)
        np.add.at(self.w, ss, t.w)
        np.add.at(self.n, ss, 1)
        u, at_last = np.unique(ss[::-1], return_index=True)
        self.last[u] = stamps[::-1][at_last]

    def all_slots(self) -> IntArray:
        """Every open slot, by (row, cluster)."""
        return self.canonical(np.flatnonzero(self.row[: self.hi] >= 0))

    def of_rows(self, rows: IntArray) -> IntArray:
        """Open slots of ``rows``, by (row, cluster): :meth:`all_slots` filtered to
        ``rows``, in O(their open passes) instead of O(all open passes)."""
        get = self.row_slots.get
        found = [s for r in np.unique(rows).tolist() for s in get(r, ())]
        return self.canonical(np.array(found, np.int64))

    def of_row(self, row: int) -> IntArray:
        """Open slots of one row, by cluster."""
        return self.canonical(np.array(self.row_slots.get(row, ()), np.int64))

    def held(self, hold: int) -> IntArray:
        """Open slots held for the holder ``hold`` (none for 0), by (row, cluster)."""
        slots = self.all_slots()
        return slots[self.hold[slots] == int(hold)] if hold else slots[:0]

    def fold(self, to: int, sl: int, a6: Array, b: Array, j6: Array, t5: Array, k: Array) -> None:
        """Add the pass of slot ``sl`` into slot ``to``: its ``a6``, ``b``, ``j6``, ``t5``
        and ``k`` as given (moved to ``to``'s frame), its other sums as they are; ``to``
        takes ``sl``'s holder and the later of their activity stamps. Both noise fits are
        settled first (they were about different references)."""
        self.a6[to] += a6
        self.b[to] += b
        self.t5[to] += t5
        if k.any() or self.k[to].any():
            self.k[to] = box_noise.settle(self.k[to]) + box_noise.settle(k)
        self.n[to] += self.n[sl]
        self.s2[to] += self.s2[sl]
        self.w[to] += self.w[sl]
        self.w2[to] += self.w2[sl]
        self.j6[to] += j6
        self.c1[to] += self.c1[sl]
        self.hold[to] = self.hold[sl]
        self.last[to] = max(self.last[to], self.last[sl])

    # ------------------------------------------------------------------ which to close
    def closable(
        self, rows: ArrayLike | None = None, clusters: ArrayLike | None = None
    ) -> IntArray:
        """Slots not held: all (no arguments), those of ``rows``, those with a cluster id in
        ``clusters`` (every landmark), or the pairs ``(rows[i], clusters[i])`` (both)."""
        slots = self.all_slots()
        if rows is not None and clusters is not None:
            keys = zip(
                np.asarray(rows).reshape(-1).tolist(),
                np.asarray(clusters).reshape(-1).tolist(),
                strict=True,
            )
            found = [self.slot.get((int(r), int(c))) for r, c in keys]
            slots = self.canonical(np.array(sorted({s for s in found if s is not None}), np.int64))
        elif rows is not None:
            slots = self.of_rows(np.asarray(rows, np.int64).reshape(-1))
        elif clusters is not None:
            slots = slots[np.isin(self.cluster[slots], np.asarray(clusters, np.int64))]
        return slots[self.hold[slots] == 0]  # held passes stay apart (see hold)

    def least_active(self, rows: IntArray, keep: int) -> IntArray:
        """The passes of ``rows`` (unique, ascending) to close so that each keeps ``keep``
        open: per row the least recently active ones not held, by (activity stamp,
        cluster), rows in order."""
        mine = self.of_rows(rows)
        mine = mine[self.hold[mine] == 0]  # held passes are never closed here
        if mine.size == 0:
            return mine
        r = self.row[mine]
        order = np.lexsort((self.cluster[mine], self.last[mine], r))
        mine, r = mine[order], r[order]
        first = np.flatnonzero(np.concatenate(([True], r[1:] != r[:-1])))
        count = np.diff(np.append(first, r.size))
        rank = np.arange(r.size) - np.repeat(first, count)
        return mine[rank < np.repeat(count, count) - keep]

    # ------------------------------------------------------------------ weighting
    def weighted(
        self, slots: IntArray, config: EstimatorConfig, ratio: Array | None = None
    ) -> tuple[Array, Array, Array]:
        """Open passes' raw sums -> what they add to ``A``, ``b`` and the pull
        (:func:`pass_weighted`; passes of imprecise rays unweighted, see
        ``pass_weighting_max_sigma_rad``), each pass's box-noise compensation taken off
        with its landmark's measured ``ratio`` (per slot; inverse-range form only) and its
        range scale eliminated first
        (:func:`~hdmap.mapping.estimator.terms.eliminate_scale`). The pull
        scales with the pass's horizontal information, ``tr_h W_p / tr_h A_p``: ``C_p``
        goes through the weighting as ``A_p`` does (``C_p ~ kappa_p A_p``)."""
        a6, b = self.a6[slots], self.b[slots]
        if ratio is not None:
            comp = self.k[slots][:, box_noise.COMP]
            a6, b = a6 - ratio[:, None] * comp[:, :6], b - ratio[:, None] * comp[:, 6:]
        a6, b = eliminate_scale(a6, b, self.t5[slots])
        c1 = self.c1[slots].copy()
        n = np.maximum(self.n[slots], 1)
        rms2 = self.s2[slots] / n
        precise = rms2 <= config.pass_weighting_max_sigma_rad**2
        if precise.any():
            # rays weighted by c (a vehicle's trust) carry c A_p: the pass's weight is
            # c W_p(A_p), that is W for c A_p with S / c (weighting passes, not only rays)
            c = np.maximum(self.w[slots][precise] / n[precise], 1e-12)
            sigma = np.asarray(config.pass_sigma_m, float)[None, :] / np.sqrt(c)[:, None]
            raw_h = a6[precise, 0] + a6[precise, 1]
            a6[precise], b[precise] = pass_weighted(a6[precise], b[precise], sigma)
            if c1.any():
                w_h = a6[precise, 0] + a6[precise, 1]
                c1[precise] *= np.divide(w_h, raw_h, out=np.zeros_like(w_h), where=raw_h > 0)
        return a6, b, c1

    def residuals(self, slots: IntArray) -> tuple[Array, Array]:
        """Open passes' box-noise residual sums and degrees of freedom
        (:func:`~hdmap.mapping.estimator.box_noise.pass_residuals`)."""
        return box_noise.pass_residuals(self.k[slots])

    # ------------------------------------------------------------------ records
    def records(self, slots: IntArray, lay: Layout) -> np.ndarray:
        """The packed open-pass records of ``slots`` in ``lay.open`` (version 4 to 7)."""
        op = np.zeros(slots.size, lay.open)
        op["cluster"], op["last"], op["n"] = (
            self.cluster[slots],
            self.last[slots],
            self.n[slots],
        )
        op["a6"], op["b"], op["s2"] = self.a6[slots], self.b[slots], self.s2[slots]
        op["w"], op["w2"] = self.w[slots], self.w2[slots]
        op["hold"], op["j6"] = self.hold[slots], self.j6[slots]
        if lay.version >= 5:
            op["c1"] = self.c1[slots]
        if lay.version >= 6:
            op["t5"] = self.t5[slots]
        if lay.version == PACK_VERSION:
            op["k"] = self.k[slots]
        return op

    def load(self, s: int, o: np.void, version: int) -> None:
        """Fill the fresh slot ``s`` from the open-pass record ``o`` of pack ``version``
        (what older versions lack as :data:`~hdmap.mapping.estimator.packing.OLD_PACK_VERSIONS`
        says)."""
        self.last[s], self.n[s] = int(o["last"]), int(o["n"])
        self.a6[s], self.b[s] = o["a6"], o["b"]
        self.s2[s] = 0.0 if version == 1 else float(o["s2"])
        self.w[s] = float(o["n"]) if version < 3 else float(o["w"])
        if version >= 4:
            self.w2[s], self.hold[s] = float(o["w2"]), int(o["hold"])
            self.j6[s] = o["j6"]
            self.c1[s] = float(o["c1"]) if version >= 5 else 0.0
            self.t5[s] = o["t5"] if version >= 6 else 0.0
            if self.k.shape[1]:  # a version 7 record read without the inverse form: dropped
                self.k[s] = o["k"] if version == PACK_VERSION else 0.0
        else:
            self.w2[s] = self.w[s] ** 2 / max(int(o["n"]), 1)
