"""The matcher's landmark table in memory: landmark records, the pending pool, vehicles'
trust records and co-visibility counts, with marks of what changed since the last save.

Landmarks are a dict of :class:`Landmark` records by id (indexed by tile); the pending
pool is one columnar :class:`PendingTile` per tile; the passes that outgrew their pending
budget have a :class:`PassBudget` record. Persistence is not here: the service's store
writes what the marks name and rebuilds the table from its database.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from hdmap.mapping.pair_counts import PairCounts
from hdmap.mapping.trust import SeenIndex, VehicleTrust
from schemas.ids import landmark_id, pass_key


class ObsRows(Protocol):
    """A table of observations (one row per ray), as the matcher's domain reads it: the
    wire ``Observations`` columns, row selection and concatenation."""

    obs_id: NDArray[np.uint64]
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    h: NDArray[np.float64]
    direction: NDArray[np.float64]
    image: NDArray[Any]
    sign_class: NDArray[Any]
    track: NDArray[Any]

    def __len__(self) -> int: ...

    def take(self, idx: NDArray[Any]) -> Any: ...

    @classmethod
    def concat(cls, parts: list[Any]) -> Any: ...


@dataclass
class Landmark:
    """One landmark's matcher-side record (the numeric state lives in the sums row)."""

    id: int
    cls: int
    home: str
    tile: str
    x: np.ndarray
    """Gating position, ECEF metres."""
    cov: np.ndarray
    """Gating covariance, local ENU, m^2."""
    row: int
    created_at: float
    view: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """Sum of the horizontal unit directions (East, North) of its rays: the side it is
    seen from (two same-class signs back to back are never one)."""
    in_view: int = 0
    """Units that had it in view (:mod:`hdmap.mapping.sightings`)."""
    seen: int = 0
    """Of those, the units that linked rays to it."""
    facing: np.ndarray = field(default_factory=lambda: np.zeros(4))
    """Gating facing as of the last re-solve of its gating estimate: azimuth, its standard
    error, the rays' spread (radians) and 1.0 where known (:class:`~hdmap.mapping.facing.
    Facing`); with ``x`` and ``cov`` what association sees of it (:mod:`hdmap.mapping.tick`)."""


class PendingTile:
    """Rays routed to one tile that wait for a landmark (columnar).

    Columns: ``obs`` (the rays, an :class:`ObsRows` table), ``vehicle`` (an object array of
    vehicle ids), ``pass_id``, ``added_at`` (event time the pending TTL is counted from),
    ``received_at`` (ingest receipt, latency tracing), ``key`` (:func:`pass_key` of each
    ray's (vehicle, pass): vectorised selection of a pass), ``tried`` (the ray has been a
    seed of an initiation attempt, :func:`hdmap.mapping.pending.initiate`; every ray is
    offered as a seed in the unit that pools it or at the end of its gating tick, and rows
    given without it are tried: a store passes the untried ones of the current tick) and
    ``saved`` (the ray is in storage; rows given without it: saved).

    Appending is O(rows appended): :meth:`add` queues its rows, and the columns are
    concatenated once, when one is next read (a gating tick's uploads add to a tile's pool
    many times before its end reads it). The rays each vehicle and each pass have here are
    counted as they come and go (:meth:`count_of`, ``per_vehicle``), so a budget check
    reads no column. Invariant: the rows read are the rows added, in the order added, less
    those :meth:`keep` dropped."""

    def __init__(
        self,
        obs: Any,
        vehicle: list[str] | NDArray[Any] | None = None,
        pass_id: NDArray[np.int64] | None = None,
        added_at: NDArray[np.float64] | None = None,
        received_at: NDArray[np.float64] | None = None,
    ) -> None:
        n = len(obs)
        self._obs = obs
        self._vehicle = np.array(list(vehicle) if vehicle is not None else [], dtype=object)
        self._pass_id = np.zeros(0, np.int64) if pass_id is None else np.asarray(pass_id, np.int64)
        self._added_at = np.zeros(0) if added_at is None else np.asarray(added_at, float)
        self._received_at = np.zeros(0) if received_at is None else np.asarray(received_at, float)
        self._key = np.array(
            [pass_key(str(v), int(p)) for v, p in zip(self._vehicle, self._pass_id, strict=True)],
            np.int64,
        )
        self._tried = np.ones(n, bool)
        self._saved = np.ones(n, bool)
        self._local = np.full((n, 6), np.nan)
        self._tail: list[tuple[Any, str, int, NDArray[np.float64], float, int, Any]] = []
        self._n = n
        self.per_vehicle: Counter[str] = Counter(self._vehicle.tolist())
        """Rays of each vehicle (the per-vehicle budget is checked at every upload)."""
        self._per_key: Counter[int] = Counter(self._key.tolist())

    def __len__(self) -> int:
        return self._n

    def count_of(self, key: int) -> int:
        """Rays of the pass with :func:`pass_key` ``key`` here."""
        return self._per_key[key]

    def add(
        self,
        obs: Any,
        vehicle: str,
        pass_id: int,
        at: float | NDArray[np.float64],
        received: float,
        local: NDArray[np.float64] | None = None,
    ) -> None:
        """Append one pass's rays with their event times ``at`` (one per ray, or one for
        all: what the pending TTL is counted from), received by ingest at ``received``;
        ``local``: their origins and directions in the tile's frame, (n, 6), if known."""
        n = len(obs)
        if not n:
            return
        key = pass_key(vehicle, pass_id)
        at_rows = np.array(np.broadcast_to(np.asarray(at, float), n))
        self._tail.append((obs, vehicle, pass_id, at_rows, received, key, local))
        self._n += n
        self.per_vehicle[vehicle] += n
        self._per_key[key] += n

    def _flush(self) -> None:
        """Concatenate the queued rows onto the columns (once for all of them)."""
        tail, self._tail = self._tail, []
        sizes = [len(t[0]) for t in tail]
        self._obs = type(tail[0][0]).concat([self._obs, *(t[0] for t in tail)])
        self._vehicle = np.concatenate(
            [
                self._vehicle,
                *(np.full(k, t[1], dtype=object) for t, k in zip(tail, sizes, strict=True)),
            ]
        )
        self._pass_id = np.concatenate(
            [self._pass_id, *(np.full(k, t[2], np.int64) for t, k in zip(tail, sizes, strict=True))]
        )
        self._added_at = np.concatenate([self._added_at, *(t[3] for t in tail)])
        self._received_at = np.concatenate(
            [self._received_at, *(np.full(k, t[4]) for t, k in zip(tail, sizes, strict=True))]
        )
        self._key = np.concatenate(
            [self._key, *(np.full(k, t[5], np.int64) for t, k in zip(tail, sizes, strict=True))]
        )
        self._local = np.concatenate(
            [
                self._local,
                *(
                    np.full((k, 6), np.nan) if t[6] is None else t[6]
                    for t, k in zip(tail, sizes, strict=True)
                ),
            ]
        )
        total = sum(sizes)
        self._tried = np.concatenate([self._tried, np.zeros(total, bool)])
        self._saved = np.concatenate([self._saved, np.zeros(total, bool)])

    def _columns(self) -> PendingTile:
        if self._tail:
            self._flush()
        return self

    @property
    def obs(self) -> Any:
        return self._columns()._obs

    @property
    def vehicle(self) -> NDArray[Any]:
        return self._columns()._vehicle

    @property
    def pass_id(self) -> NDArray[np.int64]:
        return self._columns()._pass_id

    @property
    def added_at(self) -> NDArray[np.float64]:
        return self._columns()._added_at

    @property
    def received_at(self) -> NDArray[np.float64]:
        return self._columns()._received_at

    @property
    def key(self) -> NDArray[np.int64]:
        return self._columns()._key

    @property
    def tried(self) -> NDArray[np.bool_]:
        return self._columns()._tried

    @tried.setter
    def tried(self, value: NDArray[np.bool_]) -> None:
        self._columns()._tried = np.asarray(value, bool)

    @property
    def saved(self) -> NDArray[np.bool_]:
        return self._columns()._saved

    @property
    def local(self) -> NDArray[np.float64]:
        """(n, 6): each ray's origin and direction in the tile's frame, NaN where not
        computed yet (:func:`hdmap.mapping.pending.pool_rays` fills it in: a conversion's
        rows do not depend on the rows converted with them, so a kept row is the one a
        conversion anew gives)."""
        return self._columns()._local

    def keep(self, mask: NDArray[np.bool_]) -> None:
        """Keep only the rows ``mask`` marks."""
        self._columns()
        gone = ~mask
        if gone.any():
            v, k = np.unique(self._vehicle[gone], return_counts=True)
            self.per_vehicle.subtract(dict(zip(v.tolist(), k.tolist(), strict=True)))
            self.per_vehicle = +self.per_vehicle  # vehicles without rays go
            p, k = np.unique(self._key[gone], return_counts=True)
            self._per_key.subtract(dict(zip(p.tolist(), k.tolist(), strict=True)))
            self._per_key = +self._per_key
        self._obs = self._obs.take(mask)
        self._vehicle = self._vehicle[mask]
        self._pass_id = self._pass_id[mask]
        self._added_at = self._added_at[mask]
        self._received_at = self._received_at[mask]
        self._key = self._key[mask]
        self._local = self._local[mask]
        self._tried = self._tried[mask]
        self._saved = self._saved[mask]
        self._n = int(mask.sum())


@dataclass
class PassBudget:
    """A pass that outgrew its pending budget (``MatchingConfig.pending_max_per_pass``):
    what it cost and whether it is quarantined (no more initiation attempts)."""

    vehicle: str
    pass_id: int
    evicted: int = 0
    """Rays of the pass evicted from pending pools over the budget."""
    failed: int = 0
    """Initiation attempts since it reached the budget that made no landmark (in a row)."""
    quarantined: str = ""
    """Why the pass gets no more initiation attempts ("": it does)."""
    last_at: float = 0.0
    """Event time of its last upload (the matcher's clock then): the record goes
    ``pending_ttl_s`` after it."""


class LandmarkTable:
    """Landmarks (by id, by tile), pending rays (by tile), vehicles' trust and co-visibility
    counts, with the marks of what changed (for a store to write).

    ``empty_obs`` makes an empty observation table (a new tile's pending pool)."""

    def __init__(self, empty_obs: Callable[[], Any]):
        self._empty_obs = empty_obs
        self.landmarks: dict[int, Landmark] = {}
        self.by_tile: dict[str, set[int]] = defaultdict(set)
        self.pending: dict[str, PendingTile] = defaultdict(self._empty_pending)
        self.counters: dict[str, int] = {}
        self.trust: dict[str, VehicleTrust] = {}
        self._trust_dirty: set[str] = set()
        self._trust_gone: set[str] = set()
        """Vehicles whose records were forgotten since the last save."""
        self.held_by_seen = SeenIndex()
        """The vehicles with held passes (``held_homes``), by when they were last seen:
        the probation time-out looks at the ones due only."""
        self.all_by_seen = SeenIndex()
        """Every trust record, by when its vehicle was last seen (forgetting)."""
        self.event_time = 0.0
        """The matcher's clock: event time (the observations' own capture times, each
        entry's clamped by its ingest stamp), monotone, saved with the table
        (:meth:`hdmap.mapping.matching.Matching.entry_time`)."""
        self.gating_version = 0
        """Goes up whenever what association sees of the landmarks may have changed (one
        added, removed or moved to another tile, gating estimates re-solved, a reload):
        arrays built from them are rebuilt (:func:`hdmap.mapping.tick.candidates`)."""
        self._dirty: set[int] = set()
        self._pending_dirty: set[str] = set()
        self._untried_tiles: set[str] = set()
        """Tiles whose pools got rays not yet tried as seeds (:meth:`take_untried_tiles`)."""
        self._removed_pending: list[tuple[str, int]] = []
        self._tried_saved: list[tuple[str, int]] = []
        """(vehicle, obs id) of rays in storage that became tried since the last save."""
        """(vehicle, obs id) of pending rays taken out since the last save."""
        self.covis_pairs = PairCounts()
        """Images in which two landmarks of one class were both detected: then they are two
        signs, whatever their estimates say."""
        self.copass = PairCounts()
        """Upload units that linked rays to both of two landmarks of one class: with no image
        holding both, one sign (:func:`hdmap.mapping.merge.merge_partner`)."""
        self._deleted: set[int] = set()
        self._indexed: dict[int, str] = {}
        """The tile each landmark is filed under in ``by_tile``."""
        self.passes: dict[int, PassBudget] = {}
        """Passes over their pending budget, by :func:`pass_key`."""
        self.tick_id: int | None = None
        """The current gating tick (its index in event time, :mod:`hdmap.mapping.tick`)."""
        self.tick_touched: set[int] = set()
        """Landmarks linked, started or emptied in the current gating tick: re-solved and
        offered a merge when it ends (:mod:`hdmap.mapping.tick`)."""
        self.tick_counted: set[int] = set()
        """Landmarks a unit of the current tick had in view: their sightings are checked when
        it ends."""
        self.tick_born: dict[int, int] = {}
        """Landmarks started in the current tick, with the :func:`pass_key` of the pass that
        started them (the only one that sees them before the tick ends)."""
        self._tick_dirty = False
        """The current tick changed (its index, or it ended): a store rewrites its marks."""
        self._tick_ids: set[int] = set()
        """Landmarks whose tick marks changed since the last save (a store writes those)."""
        self.unfaced: set[int] = set()
        """Landmarks loaded without a gating facing (stored before facings were kept): the
        matcher computes theirs from their sums when it restarts."""
        self._passes_dirty: set[int] = set()
        self._passes_gone: set[tuple[str, int]] = set()

    def _empty_pending(self) -> PendingTile:
        """A tile's pending pool before its first ray."""
        return PendingTile(self._empty_obs())

    # -- landmarks ------------------------------------------------------------------------

    def next_id(self, home: str) -> int:
        """A new landmark id of home tile ``home`` (the tile's counter goes up by one)."""
        n = self.counters.get(home, 0) + 1
        self.counters[home] = n
        return landmark_id(home, n)

    def removed_since_save(self) -> set[int]:
        """Landmarks removed since the last save (or load)."""
        return self._deleted

    def mark_changed(self, ids: list[int]) -> None:
        """The landmarks ``ids`` changed in place (their sums rows): a store writes them."""
        self._dirty.update(ids)

    def put(self, lm: Landmark) -> None:
        """Store ``lm`` (also after changing it in place: ``by_tile`` follows its tile)."""
        prev = self._indexed.get(lm.id)
        if prev != lm.tile:  # new, or filed under another tile
            self.gating_version += 1
        if prev is not None and prev != lm.tile:
            self.by_tile[prev].discard(lm.id)
        self._indexed[lm.id] = lm.tile
        self.landmarks[lm.id] = lm
        self.by_tile[lm.tile].add(lm.id)
        self._dirty.add(lm.id)

    @property
    def covis(self) -> dict[tuple[int, int], int]:
        """Co-visibility counts by pair (``a < b``)."""
        return self.covis_pairs.counts

    def add_covis(self, a: int, b: int, n: int = 1) -> None:
        """Landmarks ``a`` and ``b`` were detected together in ``n`` more images."""
        self.covis_pairs.add(a, b, n)

    def covis_count(self, a: int, b: int) -> int:
        """Images in which landmarks ``a`` and ``b`` were both detected."""
        return self.covis_pairs.get(a, b)

    def merge(self, keep: Landmark, drop: Landmark) -> None:
        """``drop`` becomes part of ``keep``: its view, co-visibility and co-pass counts move
        over, its record is deleted (the caller merges the sums rows)."""
        keep.view = keep.view + drop.view
        keep.in_view, keep.seen = keep.in_view + drop.in_view, keep.seen + drop.seen
        for counts in (self.covis_pairs, self.copass):
            for other, n in counts.pop(drop.id).items():
                if other != keep.id:
                    counts.add(keep.id, other, n)
        self._unlist(drop)
        self.put(keep)

    def remove(self, lm: Landmark) -> None:
        """``lm`` ends without a successor (every ray it had was taken out): its record and
        pair counts are deleted."""
        self.covis_pairs.pop(lm.id)
        self.copass.pop(lm.id)
        self._unlist(lm)

    def _unlist(self, lm: Landmark) -> None:
        """Delete ``lm``'s record."""
        self.landmarks.pop(lm.id)
        self.by_tile[self._indexed.pop(lm.id)].discard(lm.id)
        self.gating_version += 1
        self._dirty.discard(lm.id)
        self._deleted.add(lm.id)

    def near(self, tiles: list[str]) -> list[Landmark]:
        """The landmarks filed under ``tiles``, by id."""
        ids = sorted(set().union(*(self.by_tile.get(t, set()) for t in tiles)))
        return [self.landmarks[i] for i in ids]

    # -- the gating tick -------------------------------------------------------------------

    def note_tick(self, touched: set[int], counted: list[int], born: set[int], key: int) -> None:
        """A unit of the current tick touched, had in view and started these landmarks
        (started by the pass ``key``)."""
        self.tick_touched |= touched
        self.tick_counted.update(counted)
        for lid in born:
            self.tick_born[lid] = key
        self._tick_ids |= touched
        self._tick_ids.update(counted)
        self._tick_ids |= born

    def start_tick(self, tick_id: int) -> None:
        """The current gating tick is now ``tick_id``."""
        self.tick_id = tick_id
        self._tick_dirty = True

    def take_tick(self) -> tuple[list[int], list[int]]:
        """End the tick: its touched and counted landmarks (sorted), forgotten here."""
        out = sorted(self.tick_touched), sorted(self.tick_counted)
        self.tick_touched, self.tick_counted, self.tick_born = set(), set(), {}
        self._tick_ids = set()
        self._tick_dirty = True
        return out

    # -- vehicles -----------------------------------------------------------------------------

    def trust_of(self, vehicle: str) -> VehicleTrust:
        """The vehicle's record, marked to be saved (the caller is about to update it)."""
        t = self.trust.get(vehicle)
        if t is None:
            t = self.trust[vehicle] = VehicleTrust()
        self._trust_dirty.add(vehicle)
        return t

    def seen(self, vehicle: str, at: float) -> VehicleTrust:
        """The vehicle sent a unit at ``at`` (event time): its record (made if new, marked
        to be saved), last seen at ``at`` at the latest, filed for forgetting."""
        t = self.trust_of(vehicle)
        t.last_seen = max(t.last_seen, at)
        self.all_by_seen.add(vehicle, t.last_seen)
        return t

    def last_seen(self, vehicle: str) -> float:
        """When the vehicle was last seen (-inf: no record)."""
        t = self.trust.get(vehicle)
        return float("-inf") if t is None else t.last_seen

    def hold_home(self, vehicle: str, home: str) -> None:
        """The vehicle (which has a record) has held passes in home tile ``home``."""
        t = self.trust[vehicle]
        t.held_homes.add(home)
        self.held_by_seen.add(vehicle, t.last_seen)

    def forget_trust(self, vehicle: str) -> None:
        """Forget the vehicle's record (it has no held passes): it is new if it returns."""
        self.trust.pop(vehicle)
        self._trust_dirty.discard(vehicle)
        self._trust_gone.add(vehicle)
        self.held_by_seen.discard(vehicle)
        self.all_by_seen.discard(vehicle)

    def index_trust(self) -> None:
        """File every trust record in the indexes by last seen (after ``trust`` was
        rebuilt)."""
        self.held_by_seen.clear()
        self.all_by_seen.clear()
        for v, t in self.trust.items():
            self.all_by_seen.add(v, t.last_seen)
            if t.held_homes:
                self.held_by_seen.add(v, t.last_seen)

    # -- pending ----------------------------------------------------------------------------

    def add_pending(
        self,
        tile: str,
        obs: Any,
        vehicle: str,
        pass_id: int,
        at: float | NDArray[np.float64],
        received: float,
        local: NDArray[np.float64] | None = None,
    ) -> None:
        """Rays of one pass wait in ``tile``'s pool with their event times ``at`` (none:
        nothing changes); ``local``: their origins and directions in the tile's frame."""
        if len(obs):
            self.pending[tile].add(obs, vehicle, pass_id, at, received, local)
            self._pending_dirty.add(tile)
            self._untried_tiles.add(tile)

    def mark_tried(self, tile: str, rows: NDArray[np.int64]) -> None:
        """The rows ``rows`` of ``tile``'s pool have been seeds of an initiation attempt."""
        p = self.pending[tile]
        flips = rows[~p.tried[rows]]
        if flips.size:
            p.tried[flips] = True
            stored = flips[p.saved[flips]]
            if stored.size:
                self._tried_saved += list(
                    zip(p.vehicle[stored].tolist(), p.obs.obs_id[stored].tolist(), strict=True)
                )
            self._pending_dirty.add(tile)

    def take_untried_tiles(self) -> list[str]:
        """The tiles (sorted) whose pools got untried rays since the last call (those
        rays may have been tried since), forgotten here."""
        out = sorted(self._untried_tiles)
        self._untried_tiles = set()
        return out

    def drop_pending(self, tile: str, mask_remove: NDArray[np.bool_]) -> None:
        """Take the rows ``mask_remove`` marks out of ``tile``'s pool."""
        if not mask_remove.any():
            return
        p = self.pending[tile]
        ids = p.obs.obs_id[mask_remove].tolist()
        vehicles = p.vehicle[mask_remove].tolist()
        self._removed_pending += list(zip(vehicles, ids, strict=True))
        p.keep(~mask_remove)
        self._pending_dirty.add(tile)

    def budget_of(self, vehicle: str, pass_id: int) -> PassBudget:
        """The pass's budget record (made if new), marked to be saved (the caller is about
        to update it)."""
        k = pass_key(vehicle, pass_id)
        b = self.passes.get(k)
        if b is None:
            b = self.passes[k] = PassBudget(vehicle, pass_id)
            self._passes_gone.discard((vehicle, pass_id))
        self._passes_dirty.add(k)
        return b

    def drop_budgets(self, keys: list[int]) -> None:
        """Forget the budget records of passes ``keys``."""
        for k in keys:
            b = self.passes.pop(k)
            self._passes_dirty.discard(k)
            self._passes_gone.add((b.vehicle, b.pass_id))

    def pending_count(self) -> int:
        """Rays waiting in all pools."""
        return sum(len(p) for p in self.pending.values())

    def clear_marks(self) -> None:
        """Forget what changed (after a save or a load)."""
        self.covis_pairs.clear_marks()
        self.copass.clear_marks()
        self._deleted.clear()
        self._trust_dirty.clear()
        self._trust_gone.clear()
        self._dirty.clear()
        self._pending_dirty.clear()
        self._removed_pending = []
        self._tried_saved = []
        self._passes_dirty.clear()
        self._passes_gone.clear()
        self._tick_dirty = False
        self._tick_ids = set()
