"""The matcher's landmark table in memory: landmark records, the pending pool, vehicles'
trust records and co-visibility counts, with marks of what changed since the last save.

Landmarks are a dict of :class:`Landmark` records by id (indexed by tile); the pending
pool is one columnar :class:`~hdmap.mapping.pool.PendingTile` per tile; the passes that
outgrew their pending budget have a :class:`PassBudget` record. Persistence is not here:
the service's store writes what the marks name and rebuilds the table from its database.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from hdmap.mapping.evidence import EvidencePolicy, MissLedger
from hdmap.mapping.pair_counts import PairCounts
from hdmap.mapping.pool import PendingTile
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
    ranges: np.ndarray = field(default_factory=lambda: np.zeros(5))
    """Its rays' box-range sums in its home tile's frame (:mod:`hdmap.mapping.box_ranges`):
    their mean relative range at any point, which says which panel they saw."""
    in_view: int = 0
    """Units that had it in view (:mod:`hdmap.mapping.sightings`)."""
    seen: int = 0
    """Of those, the units that linked rays to it."""
    facing: np.ndarray = field(default_factory=lambda: np.zeros(4))
    """Gating facing as of the last re-solve of its gating estimate: azimuth, its standard
    error, the rays' spread (radians) and 1.0 where known (:class:`~hdmap.mapping.facing.
    Facing`); with ``x`` and ``cov`` what association sees of it (:mod:`hdmap.mapping.tick`)."""
    scale: float = float("nan")
    """Its panel's scale as association sees it: the mean relative range of its rays at
    ``x`` as of the last re-solve (:func:`hdmap.mapping.box_ranges.mean_relative_range`;
    NaN: unknown), with which a ray's box range predicts its distance
    (``GateConfig.landmark_scale``)."""
    second_facing: float = float("nan")
    """The viewing azimuth of a second street's copy merged into it (radians; NaN: none):
    that street's rays pass its facing gate (:mod:`hdmap.mapping.merge`)."""
    exist: float = float("nan")
    """Existence log-odds (:mod:`hdmap.mapping.presence`); NaN: no evidence since it was
    made (it stands at the config's start value)."""
    last_seen: float = 0.0
    """Event time of the latest pass that linked rays to it (0: none since it was made,
    ``created_at`` stands for it)."""


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
        self.held_absences: dict[str, list[tuple[int, int, float, int]]] = {}
        """Per vehicle on probation, its held "not seen" reports: (pass id, landmark id,
        time, frames) in the order they came (:func:`hdmap.mapping.presence.release_held`)."""
        self._held_absences_dirty: set[str] = set()
        self.misses = MissLedger(EvidencePolicy())
        """Counted "not seen" reports per landmark and vehicle (:mod:`hdmap.mapping.presence`;
        its policy is the matcher's)."""
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

    def hold_absences(self, vehicle: str, rows: list[tuple[int, int, float, int]]) -> None:
        """Keep reports of a vehicle on probation (:attr:`held_absences`)."""
        if rows:
            self.held_absences.setdefault(vehicle, []).extend(rows)
            self._held_absences_dirty.add(vehicle)

    def take_held_absences(self, vehicle: str) -> list[tuple[int, int, float, int]]:
        """A vehicle's held reports, forgotten here."""
        rows = self.held_absences.pop(vehicle, [])
        if rows:
            self._held_absences_dirty.add(vehicle)
        return rows

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
        if np.isnan(keep.second_facing):
            keep.second_facing = drop.second_facing
        keep.ranges = keep.ranges + drop.ranges  # the caller put drop's in keep's frame
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

    def note_tick(self, touched: set[int], counted: list[int]) -> None:
        """A unit of the current tick touched (linked to or started) and had in view these
        landmarks."""
        self.tick_touched |= touched
        self.tick_counted.update(counted)
        self._tick_ids |= touched
        self._tick_ids.update(counted)

    def start_tick(self, tick_id: int) -> None:
        """The current gating tick is now ``tick_id``."""
        self.tick_id = tick_id
        self._tick_dirty = True

    def take_tick(self) -> tuple[list[int], list[int]]:
        """End the tick: its touched and counted landmarks (sorted), forgotten here."""
        out = sorted(self.tick_touched), sorted(self.tick_counted)
        self.tick_touched, self.tick_counted = set(), set()
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
        self.take_held_absences(vehicle)
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
        self._held_absences_dirty.clear()
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
