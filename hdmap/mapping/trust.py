"""How far the matcher trusts each vehicle: a weight from its history of pass offsets.

Every unit (one pass's observations in one tile) that matches enough landmarks gets an
offset estimate (:func:`hdmap.mapping.batch_association.estimate_offset`: the shift of its
ray origins that best fits the map). An honest vehicle's offsets are its passes'
independent GNSS biases, mean zero with standard deviation ``bias_sigma_m`` per axis; a
vehicle with a bad calibration, or one shifting its data on purpose, keeps the same sign.
Per vehicle, over its units ``u`` with horizontal offsets ``o_u`` estimated with
covariance ``C_u``, an honest vehicle has ``o_u ~ N(0, B + C_u)`` with ``B = bias_sigma^2
I``; with ``W_u = (B + C_u)^-1``, ``I = sum W_u`` and ``s = sum W_u o_u``, ``chi2 = s^T
I^-1 s`` is chi-square with 2 dof. Above ``chi2_gate`` the vehicle's weight is
``(chi2_gate / chi2)^4``: its observations' reported sigmas are divided by
``sqrt(weight)`` before they are associated and summed, so it pulls the map ``weight``
times less; and its ray origins are shifted by its mean offset ``I^-1 s`` (the systematic
part is corrected, not only diluted: what it contributed before it was found out stays in
the sums at full weight).

Relative to the fleet: the map is itself pulled by a shifted vehicle (a quarter of the
passes 5.8 m off pull it 1.5 m), so every honest vehicle's offsets share that pull, and
tested against zero they look "too consistent" too. With ``relative_to_fleet`` each
vehicle's offsets are tested against the fleet's reference: the componentwise median of the
mean offsets of the vehicles with at least ``min_passes`` passes (at least 3 of them), which
the majority sets. ``s`` becomes ``s - I r`` and the shift correction ``I^-1 s - r``.

Probation (``probation_passes`` > 0): a new vehicle's rays weigh ``probation_weight`` and
its passes are *held* apart in the sums (:meth:`hdmap.mapping.estimator.LandmarkSums.accumulate`,
``hold``) until it leaves probation, once (:meth:`VehicleTrust.settle`): promoted when
``probation_passes`` of its passes had an offset and its ``chi2`` is at most
``promote_chi2`` (its held passes are then re-weighted to its full weight, exactly as if
they had come with it), or caught when its offsets are suspect (its held passes are taken
out, as if never sent). So an honest vehicle loses nothing in the end, and a shifted one
leaves nothing of what it sent before it was found out.

The units of one pass (its tiles, its upload batches) share the pass's GNSS bias: they are
combined into one offset per pass (:class:`PassOffsets`) before they enter the test.
Counting them as independent made an honest vehicle with 112 units from 16 passes look
systematic (chi2 15.7 in the Helsinki evaluation).

Also kept per vehicle: rays offered to the gate with a same-class landmark nearby and rays
that passed it; a vehicle whose rays keep failing the gate (share of failures above
``max_gate_failure``) gets a weight of ``((1 - failure) / (1 - max_gate_failure))^2``.

>>> t = VehicleTrust()
>>> for _ in range(10):
...     t.add_offset(np.array([5.0, 0.0]), np.zeros((2, 2)), 3.0)
>>> on = TrustConfig(probation_passes=0)
>>> round(t.chi2(), 1), round(t.weight(replace(on, bias_sigma_m=3.0)), 4)
(27.8, 0.0613)
>>> VehicleTrust().weight(on)
1.0
>>> VehicleTrust().weight(TrustConfig(probation_passes=10))  # new: on probation
0.05
>>> VehicleTrust().held(TrustConfig(probation_passes=10)), VehicleTrust().held(on)
(True, False)
>>> VehicleTrust().weight(TrustConfig(enabled=False))
1.0
>>> a = VehicleTrust()  # three units of one pass are one observation of its bias
>>> for _ in range(3):
...     a.add_offset(np.array([2.0, 0.0]), np.eye(2), 3.0, pass_id=7)
>>> a.n, a.passes
(0, 1)
>>> honest = VehicleTrust()
>>> for k in range(8):
...     honest.add_offset(np.array([(-1.0) ** k, 0.5]), np.zeros((2, 2)), 3.0)
>>> prob = replace(on, probation_passes=8, promote_chi2=5.99)
>>> honest.settle(prob), honest.weight(prob), honest.held(prob), honest.settle(prob)
(1, 1.0, False, None)
>>> t.settle(replace(prob, bias_sigma_m=3.0)), t.held(prob)  # shifted by 5 m: caught
(2, False)
"""

from __future__ import annotations

import heapq
from collections.abc import Callable
from dataclasses import dataclass, field, replace  # noqa: F401 (doctests)

import numpy as np

NEW, TRUSTED, CAUGHT = 0, 1, 2
"""``VehicleTrust.status``: on probation (if probation is on), promoted, caught."""


@dataclass(frozen=True)
class TrustConfig:
    enabled: bool = True
    """On by default since the test counts one offset per pass and compares with the fleet
    (module doc): in the Helsinki fleet evaluation no honest vehicle is flagged (largest
    chi2 2.1 of 10 vehicles; before, counting units and testing against zero, one was at
    15.7 and weighed 0.03). The statistics are in the matcher's stats either way
    (``weight.<vehicle>``, ``offset_chi2.<vehicle>``)."""
    bias_sigma_m: float = 4.0
    """Per-axis standard deviation of an honest pass's offset: its GNSS bias (2.5 m in the
    fleet model) plus drift, heading bias and the error of the offset estimate itself
    (offsets measured against a single sign are correlated along the road: 3.0 flagged
    honest vehicles in tests/test_rogue_vehicle.py)."""
    chi2_gate: float = 13.82
    """Beyond this (99.9% of chi-square, 2 dof) a vehicle's offsets are not chance."""
    weight_power: float = 4.0
    """Weight ``(chi2_gate / chi2)^weight_power`` beyond the gate."""
    min_passes: int = 3
    relative_to_fleet: bool = True
    """Test offsets against the fleet's median mean offset, not zero (module doc)."""
    probation_passes: int = 10
    """A new vehicle is on probation until this many of its passes had an offset and its
    chi2 is at most ``promote_chi2`` (0: no probation). While on probation its rays weigh
    ``probation_weight`` and its passes are held apart in the sums; promoted, they count in
    full; caught, they are taken out (module doc). A shifted vehicle is only found out
    after several passes: without probation what it sent before stays in the map."""
    probation_weight: float = 0.05
    probation_ttl_s: float = 86400.0
    """A vehicle still on probation this long after its last pass (by event time) has its
    held passes let go at the probation weight: they then close and fold like any pass, so
    vehicles that stop driving before they are settled do not keep passes open for ever."""
    forget_after_s: float = 2_592_000.0
    """A vehicle not seen for this long (by event time) and without held passes has its
    trust record forgotten (counted ``trust_forgotten``), so the records the matcher keeps
    and saves are those of the vehicles that drove in this window, not of every vehicle
    ever seen. A vehicle that comes back after that is new: on probation again (its rays
    held at ``probation_weight`` until it is promoted, which re-weights them to its full
    weight, or caught), its offset and gate history gone, and the fleet's reference no
    longer counts it. Thirty days: far above ``probation_ttl_s`` (a vehicle on probation
    is let go before it can be forgotten), and a vehicle silent for a month may have had
    its camera or GNSS changed, so its old record says little about it. 0: kept for ever."""
    promote_chi2: float = 4.61
    """90% of chi-square with 2 dof: promotion is for good, so it asks for offsets well
    inside the honest range (an honest vehicle passes each check with probability 0.9; at
    9.21 the shifted vehicle of tests/test_rogue_vehicle.py was promoted after 10 passes
    with chi2 6.0, its offsets being shrunk toward zero by the association's offset
    prior)."""
    max_gate_failure: float = 0.5
    """Share of gated rays failing the gate tolerated before the weight drops."""
    min_gated: int = 200
    """Rays offered to the gate before the failure share counts."""
    min_weight: float = 1e-3


@dataclass
class PassOffsets:
    """The unit offsets of a vehicle's current pass, combined (information form, without
    the pass's bias): the units of one pass share its GNSS bias, so they are one
    observation of it, not several."""

    pass_id: int = -1
    i_ee: float = 0.0
    i_en: float = 0.0
    i_nn: float = 0.0
    sx: float = 0.0
    sy: float = 0.0

    def info(self) -> np.ndarray:
        return np.array([[self.i_ee, self.i_en], [self.i_en, self.i_nn]])

    def as_row(self) -> tuple[int, float, float, float, float, float]:
        return (self.pass_id, self.i_ee, self.i_en, self.i_nn, self.sx, self.sy)


@dataclass
class VehicleTrust:
    n: int = 0
    """Passes with an offset (units of one pass count once)."""
    i_ee: float = 0.0
    i_en: float = 0.0
    i_nn: float = 0.0
    sx: float = 0.0
    sy: float = 0.0
    offered: int = 0
    passed: int = 0
    current: PassOffsets = field(default_factory=PassOffsets)
    bias_sigma_m: float = 4.0
    """Set by :meth:`add_offset` (the configured ``bias_sigma_m``)."""
    status: int = NEW
    last_seen: float = 0.0
    """Event time of its latest unit, on the matcher's trusted clock
    (:meth:`hdmap.mapping.matching.Matching.entry_time`): probation time-out, forgetting.
    Only grows."""
    held_homes: set[str] = field(default_factory=set)
    """Home tiles where this vehicle has held passes (where to send its settlement)."""
    _memo: tuple[tuple[float, ...], tuple[int, np.ndarray, np.ndarray]] | None = field(
        default=None, init=False, repr=False, compare=False
    )
    """The last :meth:`_folded` and the sums it was computed from (a unit asks for it about
    ten times: weight, chi-square, suspect, settlement; each is three 2x2 inversions)."""

    def add_offset(
        self,
        offset_en: np.ndarray,
        cov_en: np.ndarray,
        bias_sigma_m: float,
        pass_id: int | None = None,
    ) -> None:
        """One unit's offset. Units of the same ``pass_id`` (in a row) are combined into
        one observation of that pass's bias; ``None``: the unit is a pass of its own."""
        self.bias_sigma_m = bias_sigma_m
        if pass_id is None or pass_id != self.current.pass_id:
            self._fold()
            self.current = PassOffsets(-1 if pass_id is None else int(pass_id))
        c = np.asarray(cov_en, float)[:2, :2] + 1e-6 * np.eye(2)
        w = np.linalg.inv(c)
        s = w @ np.asarray(offset_en, float)[:2]
        cur = self.current
        cur.i_ee += float(w[0, 0])
        cur.i_en += float(w[0, 1])
        cur.i_nn += float(w[1, 1])
        cur.sx += float(s[0])
        cur.sy += float(s[1])
        if pass_id is None:
            self._fold()

    def _folded(self) -> tuple[int, np.ndarray, np.ndarray]:
        """(n, information, weighted sum) with the current pass included (read-only arrays,
        the same while the sums are)."""
        cur = self.current
        key = (self.n, self.i_ee, self.i_en, self.i_nn, self.sx, self.sy, cur.i_ee, cur.i_en)
        key += (cur.i_nn, cur.sx, cur.sy, self.bias_sigma_m)
        if self._memo is not None and self._memo[0] == key:
            return self._memo[1]
        out = self._fold_sums()
        for a in out[1:]:
            a.setflags(write=False)
        self._memo = (key, out)
        return out

    def _fold_sums(self) -> tuple[int, np.ndarray, np.ndarray]:
        info = np.array([[self.i_ee, self.i_en], [self.i_en, self.i_nn]])
        s = np.array([self.sx, self.sy])
        p = self.current.info()
        if p[0, 0] <= 0 and p[1, 1] <= 0:
            return self.n, info, s
        cov_p = np.linalg.inv(p)
        o_p = cov_p @ np.array([self.current.sx, self.current.sy])
        w = np.linalg.inv(cov_p + self.bias_sigma_m**2 * np.eye(2))
        return self.n + 1, info + w, s + w @ o_p

    def _fold(self) -> None:
        self.n, info, s = self._folded()
        self.i_ee, self.i_en, self.i_nn = float(info[0, 0]), float(info[0, 1]), float(info[1, 1])
        self.sx, self.sy = float(s[0]), float(s[1])
        self.current = PassOffsets()

    @property
    def passes(self) -> int:
        """Passes with an offset, the current one included."""
        return self._folded()[0]

    def mean_offset(self, ref: np.ndarray | None = None) -> np.ndarray:
        """Information-weighted mean offset (E, N), m, minus the fleet's ``ref``: the
        correction of a systematic shift."""
        n, info, s = self._folded()
        if n == 0:
            return np.zeros(2)
        m = np.linalg.solve(info, s)
        return m if ref is None else m - np.asarray(ref, float)

    def suspect(self, cfg: TrustConfig, ref: np.ndarray | None = None) -> bool:
        """Offsets too consistent to be chance (see the module doc)."""
        return cfg.enabled and self.passes >= cfg.min_passes and self.chi2(ref) > cfg.chi2_gate

    def add_gate(self, offered: int, passed: int) -> None:
        self.offered += int(offered)
        self.passed += int(passed)

    def chi2(self, ref: np.ndarray | None = None) -> float:
        return self._chi2(ref)[1]

    def _chi2(self, ref: np.ndarray | None) -> tuple[int, float]:
        """(passes, chi2 against ``ref``) from one fold of the sums."""
        n, info, s = self._folded()
        if n == 0:
            return 0, 0.0
        if ref is not None:
            s = s - info @ np.asarray(ref, float)
        return n, float(s @ np.linalg.solve(info, s))

    def held(self, cfg: TrustConfig) -> bool:
        """On probation: its passes are held apart in the sums."""
        return cfg.enabled and cfg.probation_passes > 0 and self.status == NEW

    def settle(self, cfg: TrustConfig, ref: np.ndarray | None = None) -> int | None:
        """Leave probation if the evidence is in: returns the new status (``TRUSTED`` or
        ``CAUGHT``) once, else None."""
        if not self.held(cfg):
            return None
        n, c = self._chi2(ref)
        if n >= cfg.min_passes and c > cfg.chi2_gate:
            self.status = CAUGHT
        elif n >= cfg.probation_passes and c <= cfg.promote_chi2:
            self.status = TRUSTED
        else:
            return None
        return self.status

    def weight(self, cfg: TrustConfig, ref: np.ndarray | None = None) -> float:
        if not cfg.enabled:
            return 1.0
        w = 1.0
        n, c = self._chi2(ref)
        if cfg.probation_passes > 0 and self.status != TRUSTED:
            w = cfg.probation_weight
        if n >= cfg.min_passes and c > cfg.chi2_gate:
            w *= (cfg.chi2_gate / c) ** cfg.weight_power
        if self.offered >= cfg.min_gated:
            fail = 1.0 - self.passed / self.offered
            if fail > cfg.max_gate_failure:
                w *= ((1.0 - fail) / (1.0 - cfg.max_gate_failure)) ** 2
        return max(w, cfg.min_weight)

    def as_row(self) -> tuple[int, float, float, float, float, float, int, int]:
        return (
            self.n,
            self.i_ee,
            self.i_en,
            self.i_nn,
            self.sx,
            self.sy,
            self.offered,
            self.passed,
        )


class FleetOffsets:
    """The fleet's reference offset (E, N): the componentwise median of the mean offsets of
    the vehicles with at least ``min_passes`` passes (None with fewer than 3 of them, or
    when ``relative_to_fleet`` is off). Each vehicle's mean is kept as it changes, so the
    reference costs O(vehicles) numpy work, once per change.

    >>> fo = FleetOffsets(TrustConfig())
    >>> for i, o in enumerate(([-1.5, -0.9], [-1.4, -1.0], [-1.6, -0.8], [4.3, 2.2])):
    ...     v = VehicleTrust()
    ...     for _ in range(5):
    ...         v.add_offset(np.array(o), np.zeros((2, 2)), 4.0)
    ...     fo.update(f"v{i}", v)
    >>> fo.reference().round(2).tolist()
    [-1.45, -0.85]
    """

    def __init__(self, cfg: TrustConfig):
        self.cfg = cfg
        self._means: dict[str, np.ndarray] = {}
        self._ref: np.ndarray | None = None
        self._stale = False

    def update(self, vehicle: str, t: VehicleTrust) -> None:
        if t.passes >= self.cfg.min_passes:
            self._means[vehicle] = t.mean_offset()
        else:
            self._means.pop(vehicle, None)
        self._stale = True

    def forget(self, vehicle: str) -> None:
        """The vehicle's record is gone: it no longer counts in the reference."""
        if self._means.pop(vehicle, None) is not None:
            self._stale = True

    def reference(self) -> np.ndarray | None:
        """The reference over the vehicles updated so far."""
        if self._stale:
            self._stale = False
            self._ref = None
            if self.cfg.relative_to_fleet and len(self._means) >= 3:
                self._ref = np.median(np.array(list(self._means.values())), axis=0)
        return None if self._ref is None else self._ref.copy()


class SeenIndex:
    """Vehicles filed by a lower bound of their ``last_seen`` (a heap), so that finding
    the ones last seen before a cutoff looks at those and few others, not at every vehicle.

    A vehicle is filed under its ``last_seen`` when it is added. ``last_seen`` only grows
    (it is a max), so the key stays a lower bound without being updated as the vehicle
    drives: :meth:`due` pops the keys below the cutoff, looks the vehicle's ``last_seen``
    up, hands it out if it is below the cutoff too, and otherwise files it again under its
    ``last_seen`` (which is at or above the cutoff: looked at once per call). A call's
    work is the vehicles due, the vehicles seen since they were filed whose key the
    cutoff passed, and the leftover entries of vehicles taken out (each once); the heap
    is rebuilt when leftovers outnumber the vehicles filed.

    >>> seen = {"a": 10.0, "b": 20.0, "c": 30.0}
    >>> ix = SeenIndex()
    >>> for v in "cab":
    ...     ix.add(v, seen[v])
    >>> seen["a"] = 40.0                     # drove again: key 10 is now a lower bound
    >>> ix.due(25.0, seen.__getitem__), ix.visited, len(ix)
    (['b'], 2, 2)
    >>> ix.due(25.0, seen.__getitem__), ix.visited  # a was filed again under 40
    ([], 2)
    >>> ix.discard("c"); ix.due(100.0, seen.__getitem__), len(ix)
    (['a'], 0)
    """

    def __init__(self) -> None:
        self._heap: list[tuple[float, str]] = []
        self._key: dict[str, float] = {}
        self.visited = 0
        """Heap entries :meth:`due` looked at, over all calls (what the walks cost)."""

    def __len__(self) -> int:
        return len(self._key)

    def __contains__(self, vehicle: str) -> bool:
        return vehicle in self._key

    def add(self, vehicle: str, key: float) -> None:
        """File ``vehicle`` under ``key`` (at most its ``last_seen``); one already filed
        keeps its key."""
        if vehicle in self._key:
            return
        self._key[vehicle] = key
        heapq.heappush(self._heap, (key, vehicle))

    def discard(self, vehicle: str) -> None:
        """Take ``vehicle`` out (if filed)."""
        if self._key.pop(vehicle, None) is not None and len(self._heap) > 2 * len(self._key) + 64:
            self._heap = [(k, v) for v, k in self._key.items()]
            heapq.heapify(self._heap)

    def clear(self) -> None:
        self._heap.clear()
        self._key.clear()

    def due(self, cutoff: float, last_seen: Callable[[str], float]) -> list[str]:
        """The vehicles filed whose ``last_seen(vehicle)`` is below ``cutoff``, taken out,
        in name order."""
        out = []
        heap = self._heap
        while heap and heap[0][0] < cutoff:
            key, v = heapq.heappop(heap)
            self.visited += 1
            if self._key.get(v) != key:
                continue  # taken out (and maybe filed again) since
            seen = last_seen(v)
            if seen < cutoff:
                del self._key[v]
                out.append(v)
            else:
                self._key[v] = seen
                heapq.heappush(heap, (seen, v))
        return sorted(out)
