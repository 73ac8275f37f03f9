"""The matcher's domain: its knobs (:class:`MatchingConfig`), its in-memory state
(:class:`Matching`: the landmark table, the gating sums, open passes, the fleet's offsets)
and what one obs entry produces for each landmark home tile (:class:`AssocOutput`).

The steps that work on it are functions of a :class:`Matching`: one unit's association
(:mod:`hdmap.mapping.unit`), linking rays and re-solving gating estimates
(:mod:`hdmap.mapping.linking`), landmarks from pending rays (:mod:`hdmap.mapping.pending`),
vehicles leaving probation (:mod:`hdmap.mapping.probation`) and merging landmarks of one
sign (:mod:`hdmap.mapping.merge`). Nothing here does I/O; the wall clock (only to
refuse ingest stamps far in the future) and the counters are given.

Every time that decides what the map contains (pending TTL, pass closing, probation
time-outs, forgetting trust records, pass budgets) is event time: the observations' own
capture times, each entry's clamped by its trusted ingest stamp, on the matcher's monotone
clock (:meth:`Matching.entry_time`), never the wall clock and never the largest time a
batch carries. The same entries in the same order give the same map whenever and however
fast they are applied: live, a day late in one bulk, or replayed
(:mod:`hdmap.mapping.event_time`).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdmap.geo.geodesy import GEODESY
from hdmap.geo.tiles import TileFrames, neighbours, quadkeys_of
from hdmap.mapping.association import GateConfig
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from hdmap.mapping.facing import Facing, facing_from_sums
from hdmap.mapping.initiation import InitConfig
from hdmap.mapping.landmarks import Landmark, LandmarkTable
from hdmap.mapping.presence import PresenceConfig
from hdmap.mapping.quiet import (
    COMPACT_MIN_ROWS,
    QuietPasses,
    SweepPeriods,
    compact_rows,
    note_open,
)
from hdmap.mapping.sightings import SightingConfig
from hdmap.mapping.trust import FleetOffsets, TrustConfig, VehicleTrust


def gating_estimator() -> EstimatorConfig:
    """The matcher's estimator: the solver's, with the plug-in meat
    (``integrated_meat`` off). The gate and merge thresholds were measured with it; the
    integrated meat widens young landmarks' gates, and on the four-seed fleet evaluation
    that turned 0/0/0/0 duplicated landmarks into 0/0/2/0 and moved coverage from 30 passes
    from 0.969 to 0.981 on seed 3 (docs/estimator.md section 6)."""
    return EstimatorConfig(integrated_meat=False)


@dataclass(frozen=True)
class MatchingConfig:
    """How the matcher gates, starts, weighs and merges landmarks."""

    gate: GateConfig = field(default_factory=GateConfig)
    init: InitConfig = field(default_factory=InitConfig)
    estimator: EstimatorConfig = field(default_factory=gating_estimator)
    gate_probation_full: bool = True
    """Rays of a vehicle on probation count in full in the matcher's own (gating) sums; the
    solver's, which make the map, get the probation weight."""
    pending_ttl_s: float = 3600.0
    """Unmatched rays captured this long (event time) before the matcher's clock are
    dropped (counted ``expired``): rays of passes hours apart never start a landmark
    together, however they arrive (a day's drives uploaded at once included)."""
    pending_max_per_pass: int = 256
    """Most rays of one pass left waiting in one tile's pending pool after an upload's
    initiation attempt; past it the pass's oldest there are evicted (counted
    ``pending_evicted``) and the pass gets a budget record (see ``quarantine_after``).
    Initiation looks at a pass's waiting rays around the tile, so this bounds what one
    upload makes it look at (9 tiles x this, and the upload). The budget is applied after
    the attempt: an upload into a tile with no landmark yet pools all its rays first (more
    than 256 in one tile in the fleet evaluation's first round). Honest passes keep few
    rays that never make a landmark (at most 20 per pass, 13 per tile and pass, at the end
    of the fleet evaluation); a pass held in one tile by a hostile or broken vehicle (a
    parked car, image indices that restart in every upload) fills it. 0: no limit."""
    pending_max_per_vehicle: int = 1024
    """Most rays of one vehicle (all its passes) waiting in one tile's pending pool; past
    it its oldest there are evicted (counted ``pending_evicted``): a vehicle that opens a
    new pass with every upload is held to a budget too. Four times the per-pass budget: a
    vehicle that crosses a tile many times within ``pending_ttl_s`` keeps a few strays
    from each pass (at most 57 per tile at the end of the fleet evaluation, 16 passes a
    vehicle). 0: no limit."""
    init_reseed_max: int = 64
    """While a pass has at most this many waiting rays of a class around the tile, all of
    them seed candidates again at each initiation attempt (the full re-run, exact, and
    cheap that small); above it only the rays not tried as seeds yet do (in practice the
    ones the upload just pooled, counted ``init_new_seeds_only``), with all of them as
    possible members: an attempt's work is then the upload's rays times the pass's, not
    the pass's squared (the invariant is at :func:`hdmap.mapping.pending.initiate`).
    Honest passes keep few waiting rays, and the rays of an upload into a tile with no
    landmark yet are all new: the fleet evaluation's uploads (seed 0) replayed through the
    matcher give the full re-run's map to the last bit (9 attempts seeded from the new
    rays only). With new seeds only at every size they did not: the greedy
    grows from the newest rays rather than the oldest, and that made 332 landmarks rather
    than 321 (more merges after; 230 rather than 232 in the end). 0: no limit (every
    attempt re-runs in full, O(P^2) in the pass's waiting rays P: the old way)."""
    quarantine_after: int = 8
    """A pass that reached ``pending_max_per_pass`` and then made no landmark in this many
    initiation attempts in a row is quarantined (reason ``no_landmark_at_budget``, counted
    ``passes_quarantined``): no more initiation attempts for it; its rays still link to
    landmarks around them and wait for adoption by the landmarks other passes start. An
    honest pass never reaches the budget; eight attempts leave a pass that fills it a
    chance with the rays it sends after the eviction. 0: never."""
    close_passes_after_s: float = 7200.0
    """Close a pass in the gating sums once no ray of it has been linked for this long
    (event time, :mod:`hdmap.mapping.quiet`; 0: open until evicted). Above
    ``pending_ttl_s``: a pending ray can still be linked until it expires."""
    compact_min_rows: int = COMPACT_MIN_ROWS
    """The gating sums drop the rows of retired and merged landmarks once this many (and
    as many as live landmarks) have piled up, after a transaction's save
    (:func:`hdmap.mapping.quiet.compact_rows`, counted ``sums_rows_dropped``): memory
    follows the live map, not every landmark ever made. The map is the same to the bit
    whatever the value."""
    sweep_every_s: float = 60.0
    """Expiry, forgotten budgets and pass closing run when the matcher's clock enters a new
    period of this length (event time; :func:`hdmap.mapping.event_time.advance`): at the
    same entries live and on a replay, and once a minute of data rather than per entry."""
    tick_s: float = 1.0
    """Gating tick (event time, :mod:`hdmap.mapping.tick`): the units of one tick are
    associated with the landmarks as the tick found them; the rays they leave waiting are
    tried as seeds of new landmarks, and the landmarks they touched are re-solved and
    merged, when the clock enters the next tick. 0: after every unit (one unit, one
    tick)."""
    tick_lag_s: float = 3.0
    """A unit at most this far behind the matcher's clock (event time) joins the clock's
    gating tick; one further behind (a late or bulk upload) goes by its own time
    (:func:`hdmap.mapping.tick.tick_of`). Live uploads reach the matcher seconds out of
    event-time order (vehicles pace and batch their uploads, ingest batches them): with the
    lag at ``tick_s`` (1 s) a load test cut every second of traffic into 4-18 ticks. A
    vehicle that uploads a pass when it ends sends its first tiles up to the pass's length
    behind the clock, and each of them ends the live tick and has one of its own (a load
    test at 8,000 obs/s: 4,252 ticks of about one unit, 177 us CPU per observation in a
    replay; with 60 s, 789 ticks and 87 us; end to end 7,000 obs/s against 4,000:
    docs/experiments/2026-12-tick-lag.md).

    Pitfall, why it is not longer: passes that share a tick do not see each other's new
    landmarks; where adoption's gate refuses a pass's rays (it offers them alone, without
    the offset the pass's other rays would fix) they start copies, merged later. With 60 s
    the fleet evaluation's logs replayed (1,200 passes, four seeds each) give confirmed maps
    on par with 3 s, but on the real phone errors 23 more young candidates paired with no
    sign, all born from the last uploads before the map was read (bulk uploads within the
    lag of the clock): a transient the evaluation counts as false landmarks
    (docs/experiments/2026-12-tick-lag.md; 120 s: 18 more a seed). A region merge brings its
    parts to one position of ingest's log (:func:`hdmap.ops.region.cut_at_one_position`), so
    merges no longer limit the lag. What a split does not keep, at any lag: a part's clock
    is the latest of its own units, so a unit of one part that the whole would have seen
    behind another part's later units (within the lag) joins its part's tick, not the
    whole's: the same map only where the regions' traffic is in event-time order
    (tests/integration/test_region_split.py)."""
    time_tolerance_s: float = 300.0
    """An obs entry whose ingest time (``received_at``) is more than this ahead of the
    matcher's wall clock does not move the matcher's clock (counted ``time_clamped``; see
    :meth:`Matching.entry_time`). Ingest stamps an entry before the matcher applies it, so
    an honest entry is behind the matcher's wall clock by the two hosts' clock skew at
    most; five minutes is far above the skew of clocks kept by NTP, and far below the
    probation time-out (a day) that the clock drives."""
    trust: TrustConfig = field(default_factory=TrustConfig)
    """Per-vehicle weights from the history of its pass offsets and gate failures."""
    gate_bias_floor: bool = True
    """Gate with the solution's covariance plus the pass-bias prior over its passes
    (``diag(bias^2) / G``): the between-pass covariance of a few passes is itself noisy,
    and a gate that is too tight splits one sign into several landmarks."""
    group_check: bool = True
    """The rays of one unit given to one landmark must meet near it: their own
    triangulation (origins moved by the unit's offset) against the landmark, chi-square
    (3 dof) under both covariances and the offset's. Rays of a neighbouring sign of the
    class pass the per-ray gate one by one, but they meet at their own sign.

    Pitfall: the triangulation assumes white noise. A unit's tracks of one sign from two
    streets share the pass's heading error, which moves a far track's meeting point by its
    range times the angle; together they then fail a right landmark (the fleet evaluation's
    seed 0: 89 of 577 passes' groups of sign 99, 64 holding 99's rays only). Testing each
    track alone, a heading estimated with the offset, or the rays' azimuth variance as a
    shared rotation of the group moved the false landmarks elsewhere rather than removing
    them (docs/experiments/2026-12-group-check-by-track.md)."""
    group_chi2: float = 16.27
    """Largest chi-square (3 dof; 16.27 = 99.9 %) of a group's triangulation against its
    landmark."""
    group_min_rays: int = 2
    """Smallest group that is checked (one ray does not triangulate)."""
    presence: PresenceConfig = field(default_factory=PresenceConfig)
    """Existence per landmark from the passes that detect it and the vehicles' "not seen"
    reports; revoked landmarks leave the map (:mod:`hdmap.mapping.presence`)."""
    sightings: SightingConfig = field(default_factory=SightingConfig)
    """Landmarks that the passes having them in view do not detect are retired
    (:mod:`hdmap.mapping.sightings`: second copies of a sign, counted ``retired_unseen``)."""
    track_drop_unlinked: bool = True
    """Rays of a track that went to a landmark without them (outside the gate) are dropped
    rather than left to start another landmark of the same sign."""
    merge: bool = True
    """Merge landmarks found to be one sign (see :mod:`hdmap.mapping.merge`)."""
    merge_chi2: float = 16.27
    """Largest chi-square (3 dof; 16.27 = 99.9 %) of the difference of two estimates, under
    the sum of their gating covariances."""
    merge_max_m: float = 10.0
    """Largest horizontal distance between two landmarks that may merge."""
    merge_max_covis: float = 0.2
    """Largest share of the smaller landmark's rays in images that also detected the other.
    Two signs seen from the same roads are detected together in most images where both are
    in view (0.33-0.79 over the fleet evaluation's four seeds); two landmarks of one sign
    are detected together only through the other signs' rays one of them took by mistake
    (0.11-0.28). 0.2 lets those duplicates merge (at 0.1, seed 0's sign 130 stayed two
    landmarks 0.1 m apart, at 0.13) and stays below the lowest share of two signs."""
    merge_min_view_cos: float = 0.5
    """Smallest cosine between the two landmarks' mean viewing directions."""
    merge_copy_units: int = 10
    """Copies (0: off): two landmarks of one class at most ``merge_copy_max_m`` apart that
    this many upload units linked rays to both, at least ``merge_copy_share`` of the
    smaller one's passes, seen from directions at most ``merge_copy_max_deg`` apart, and
    detected in one image in at most ``merge_copy_max_covis`` of the smaller one's rays,
    are one sign whatever their estimates say: the passes that see one see the other, and
    never both at once. Over the four seeds at 1,200 passes every pair of distinct signs
    within 16 m that is (almost) never in one image faces 78-178 degrees away from the
    other (corners, back to back); a copy made of a sign's own rays 3-12 m off its
    landmark faces the same way (docs/experiments/2026-12-unpaired-landmark-kinds.md)."""
    merge_copy_share: float = 0.3
    merge_copy_max_m: float = 15.0
    merge_copy_max_deg: float = 45.0
    merge_copy_max_covis: float = 0.03
    merge_apart_max_m: float = 8.0
    """Copies seen from different passes (0: off): two landmarks of one class at most this
    far apart, facing at most ``merge_copy_max_deg`` apart, each with
    ``merge_apart_min_rays`` rays or more, and detected in one image in at most
    ``merge_apart_max_covis`` of the smaller one's rays, are one sign whatever their
    estimates and their passes say. Two signs that close facing one way are in one image
    whenever a car sees either (0.16-0.51 of the rays of every such pair of distinct signs
    over the fleet evaluation's four seeds on both noises); a sign seen from two routes
    whose biases differ can end as two landmarks 3-7 m apart, each under a tight
    covariance and with its own passes (co-visibility 0-0.04, co-passes 0.02-0.15: neither
    the estimates' gate nor ``merge_copy_units`` joins them). Pitfall: a sign that hides
    its neighbour from every road (a wall between two panels facing one way) would merge
    too; the simulator has no occlusion (docs/experiments/2026-12-copies-apart.md)."""
    merge_apart_max_covis: float = 0.05
    merge_apart_min_rays: int = 100
    """Fewer rays do not tell: two signs detected together in 16 % of the images (the
    fewest of any pair within 8 m) show 5 or fewer shared images in 100 rays with
    binomial probability 0.0007."""
    merge_ghost_max_m: float = 25.0
    """Second-street copies (0: off): bearings from one street fix a sign's range poorly,
    so a second street whose rays the facing gate keeps off the sign's landmark makes a
    copy 5-13 m along its line of sight. A same-class landmark at most this far away,
    facing at least ``merge_ghost_min_deg`` away, that lies on a landmark's line of sight
    (within ``merge_ghost_across_m``) is the same sign when the first one's rays' box
    ranges put their panel there: their mean relative range at it equals its own rays'
    there (within ``merge_ghost_tol`` in log; one panel, one size) and differs at their
    own position (:func:`hdmap.mapping.merge.ghost_partner`). Both need
    ``merge_ghost_min_passes`` passes and may share images in at most
    ``merge_apart_max_covis`` of the smaller one's rays. Over the four seeds at 1,200
    passes on both noises, second-street copies agree within 0.02 and two signs differ by
    0.10 or more (docs/experiments/2026-12-two-street-ghosts-ranges.md)."""
    merge_ghost_across_m: float = 1.5
    merge_ghost_min_deg: float = 45.0
    """Not along one street: copies there (phone errors' shared heading, 11-22 m along
    the line of sight) have the same panel too, but merged their bearings still fix the
    range poorly, and a young copy near the sign folded into an old one 15-25 m off ended
    off (docs/experiments/2026-12-two-street-ghosts-ranges.md)."""
    merge_second_facing: bool = True
    """A merge of two landmarks facing ``merge_ghost_min_deg`` or more apart (one sign
    seen from two streets) gives the kept one the other's facing as a second one
    (``Landmark.second_facing``): the second street's rays pass its facing gate from then
    on instead of starting the next copy."""
    merge_ghost_tol: float = 0.05
    merge_ghost_min_passes: int = 20
    merge_min_passes: int = 2
    """Both landmarks need this many passes (a one-pass estimate carries its pass's whole
    bias). With onboard tracks, co-visibility tells two signs apart reliably, so two passes
    are enough: on the four seeds, 2 rather than 5 cut the young map's duplicates at 3-4
    passes from 13-48 to 0-5 (with ``merge_max_covis`` 0.1; 2 / 0 / 9 / 3 with 0.2).
    A landmark looks for a partner at each of its passes up to ``merge_every_pass_until``,
    then at every third (the search is most of a unit's cost otherwise)."""
    merge_every_pass_until: int = 10
    """Passes up to which a landmark looks for a partner at every pass. A young second copy
    looked only at every third pass past 4: seed 3's sign 7 ended its run as two confirmed
    landmarks 1.9 m apart (chi-square 0.1), the copy at 5 passes, so it counted as a
    duplicate until one of them next looked."""
    provisional_passes: int = 0
    """If > 0, gating estimates follow the landmark's solution from this many passes on
    (before the estimator's ``min_clusters``, with the pass-bias prior in the covariance;
    see :mod:`hdmap.mapping.estimator.provisional`). Off: until ``min_clusters`` passes the gate
    uses the initiating pass's triangulation with the full pass bias, which the fleet
    evaluation found far safer (with 2: association right 0.51 vs 0.81 at 20-29 passes,
    many more duplicates; a 2-4 pass sandwich covariance is too small to gate with)."""


@dataclass
class AssocOutput:
    """What one obs entry produces for one landmark home tile (the assoc output being built)."""

    vehicles: list[str] = field(default_factory=list)
    links: list[tuple[int, int, int]] = field(default_factory=list)
    """(landmark id, vehicle index, pass id) per linked ray."""
    received_at: list[float] = field(default_factory=list)
    weight: list[float] = field(default_factory=list)
    held: list[bool] = field(default_factory=list)
    obs: list[Any] = field(default_factory=list)
    """The linked rays, one observation table per link call (in ``links`` order)."""
    trust: list[tuple[int, bool, float]] = field(default_factory=list)
    """(vehicle index, dropped, weight): vehicles leaving probation, their held passes
    dropped or released at ``weight``."""
    created: list[tuple[int, int, float, float, float]] = field(default_factory=list)
    """(id, class, lat, lon, h) of new landmarks."""
    retired: list[tuple[int, int]] = field(default_factory=list)
    """(retired id, id it merged into)."""
    ended: list[int] = field(default_factory=list)
    """Retired without a successor (emptied: every ray taken out; revoked)."""
    existence: dict[int, tuple[int, float, int, float, float]] = field(default_factory=dict)
    """Landmarks whose existence changed: (id, probability, state, first seen, last seen)
    (:func:`hdmap.mapping.presence.row`)."""

    def vehicle_index(self, v: str) -> int:
        """Index of vehicle ``v`` in ``vehicles`` (added if new)."""
        if v not in self.vehicles:
            self.vehicles.append(v)
        return self.vehicles.index(v)


def new_output() -> defaultdict[str, AssocOutput]:
    """An empty output: one :class:`AssocOutput` per home tile, made as it is needed."""
    return defaultdict(AssocOutput)


class Matching:
    """The matcher's in-memory state and what the domain steps share.

    ``state`` is the landmark table, ``sums`` the gating sums (rows of ``state``'s
    landmarks), ``quiet`` the open passes, ``fleet`` the fleet's pass offsets and ``out``
    the output of the batch being applied. ``tally(name, n)`` counts events; ``clock``
    gives wall-clock seconds, used only to refuse ingest stamps far ahead of it
    (:meth:`entry_time`); every age is on :attr:`now`, the event-time clock."""

    def __init__(
        self,
        config: MatchingConfig,
        state: LandmarkTable,
        zoom: int,
        region: list[str],
        tally: Callable[[str, int], None],
        clock: Callable[[], float],
    ):
        self.config = config
        self.state = state
        state.misses.policy = config.presence.evidence
        self.zoom = zoom
        self.region = region
        self.tally = tally
        self.clock = clock
        self.frames = TileFrames()
        self._areas: dict[str, list[str]] = {}
        self._sums = LandmarkSums(config.estimator)
        self.quiet = QuietPasses(config.close_passes_after_s, clock=lambda: self.now)
        self.sweeps = SweepPeriods(config.sweep_every_s)
        """When the clock last entered a new sweep period (``sweep_every_s``)."""
        self.fleet = FleetOffsets(config.trust)
        self.flagged: dict[str, tuple[float, float]] = {}
        """(weight, offset chi2) of the vehicles stats show: downweighted or suspect."""
        self.out: defaultdict[str, AssocOutput] = new_output()
        self.unsummed: list[tuple[Any, Any, Rays, Any]] = []
        """Links not yet added to the gating sums (rows, pass keys, rays, hold keys):
        :meth:`flush_links`."""
        self.unsummed_ids: list[np.ndarray] = []
        """The landmark id of each held link's row (a store keeps held links by id: rows
        are numbered anew when the sums are reloaded)."""
        self.held_saved = 0
        """Held links a store has already written (:meth:`held_to_save`)."""
        self.held_flushed = False
        """The sums took the held links since the store last wrote them."""
        self.candidate_arrays: dict[str, tuple[int, Any]] = {}
        """Per tile, the landmarks its units see as arrays, with the landmarks'
        ``gating_version`` they were built at (:func:`hdmap.mapping.tick.candidates`)."""
        self.tick_serial = 0
        """Counts the gating ticks begun in this process (:func:`hdmap.mapping.tick.enter`):
        an association made in one is not used in another."""

    def restart(self, sums: LandmarkSums) -> None:
        """After ``state`` was (re)loaded with ``sums``: open passes are quiet from now on,
        the fleet's offsets and the flagged vehicles follow the trust records."""
        self._sums = sums
        self.unsummed, self.unsummed_ids = [], []
        self.held_saved, self.held_flushed = 0, False
        if self.state.unfaced:
            lms = [self.state.landmarks[i] for i in sorted(self.state.unfaced)]
            for lm, fk in zip(lms, facings_of(self, lms).rows(), strict=True):
                lm.facing = fk
                self.state.put(lm)
            self.state.unfaced = set()
        self.sweeps.restart(self.now)
        self.quiet.clear()
        note_open(self.quiet, self.sums, self.state)
        self.flagged = {}
        self.fleet = FleetOffsets(self.config.trust)
        for v, t in sorted(self.state.trust.items()):
            self.fleet.update(v, t)
        ref = self.fleet_ref()
        for v, t in self.state.trust.items():
            self.note_trust(v, t, ref)

    @property
    def sums(self) -> LandmarkSums:
        """The gating sums, with every link held so far added (:meth:`flush_links`)."""
        self.flush_links()
        return self._sums

    def new_rows(self, k: int, x0: np.ndarray) -> np.ndarray:
        """Rows for ``k`` new landmarks at ``x0`` in the gating sums, without flushing: a new
        row touches none of the held links' rows (they are added after it as they came)."""
        return self._sums.new_rows(k, x0)

    def flush_links(self) -> None:
        """Add the links held since the last flush to the gating sums, in one call.

        :func:`hdmap.mapping.linking.link` holds a link's rays rather than adding them at
        once: the sums after a list of rays do not depend on how it is cut into
        ``accumulate`` calls, so one call for a gating tick's links gives the same sums as
        one per unit, for one call's fixed cost. Reading :attr:`sums` flushes first (a
        re-solve, the facings, a merge, a settlement, closing quiet passes, saving the
        state all do), so nothing sees the sums without the links made before."""
        parts, ids = self.unsummed, self.unsummed_ids
        self.unsummed, self.unsummed_ids = [], []
        if parts:  # a store empties its held links: the rows they went to are written
            self.held_saved, self.held_flushed = 0, True
            lms = self.state.landmarks
            self.state.mark_changed(sorted({i for i in np.concatenate(ids).tolist() if i in lms}))
        self._sums.accumulate_parts(parts)

    def compact_rows(self) -> int:
        """Drop the gating sums' rows of gone landmarks once they pile up
        (:func:`hdmap.mapping.quiet.compact_rows`), the held links' rows renumbered with
        them. Returns the rows dropped; the map is the same to the bit."""
        if self.unsummed_ids:
            held = np.concatenate(self.unsummed_ids)
            if not np.isin(held, np.fromiter(self.state.landmarks, np.uint64)).all():
                return 0  # not after a save (held_to_save flushes those): wait for one
        new_of = compact_rows(
            self.quiet, self._sums, self.state.landmarks.values(), self.config.compact_min_rows
        )
        if new_of is None:
            return 0
        self.unsummed = [(new_of[r], *rest) for r, *rest in self.unsummed]
        return int((new_of < 0).sum())

    def hold_link(self, item: tuple[Any, Any, Rays, Any], ids: np.ndarray) -> None:
        """Hold one link call's rays for the gating sums (:meth:`flush_links`): (rows, pass
        keys, rays, hold keys), and the landmark ids of the rows."""
        self.unsummed.append(item)
        self.unsummed_ids.append(ids)

    def hold_again(self, held: list[tuple[np.ndarray, tuple[Any, Any, Rays, Any]]]) -> None:
        """After a restart: the held links a store kept, (landmark ids, item with rows of
        the reloaded sums), in their order; they count as written."""
        for ids, item in held:
            self.hold_link(item, ids)
        self.held_saved, self.held_flushed = len(self.unsummed), False

    def held_to_save(self) -> tuple[bool, int, list[tuple[np.ndarray, tuple[Any, Any, Rays, Any]]]]:
        """What a store writes of the held links: whether the sums took them since it last
        did (its copy empties), the position of the first new one and the new ones (landmark
        ids, item); then they count as written. A held link to a landmark that is gone
        flushes them all first (its row has no id to be kept by)."""
        gone = self.state.removed_since_save()
        if gone and self.unsummed_ids:
            held = np.concatenate(self.unsummed_ids)
            if np.isin(held, np.array(sorted(gone), np.uint64)).any():
                self.flush_links()
        start = self.held_saved
        new = list(zip(self.unsummed_ids[start:], self.unsummed[start:], strict=True))
        flushed = self.held_flushed
        self.held_saved, self.held_flushed = len(self.unsummed), False
        return flushed, start, new

    @property
    def sums_as_held(self) -> LandmarkSums:
        """The gating sums without the held links (what a store packs: it keeps the held
        links apart, :meth:`held_to_save`)."""
        return self._sums

    @property
    def now(self) -> float:
        """The matcher's clock: event time, monotone (:meth:`entry_time`)."""
        return self.state.event_time

    def is_ahead(self, received_at: float) -> bool:
        """An ingest stamp too far ahead of the wall clock to be trusted."""
        return received_at > self.clock() + self.config.time_tolerance_s

    def entry_time(self, received_at: float, capture_t: np.ndarray) -> float:
        """The event time of an obs entry whose rays were captured at ``capture_t`` and that
        ingest stamped ``received_at``; the matcher's clock advances to it.

        An entry's event time is its latest capture time, but never later than its ingest
        stamp (a vehicle's clock is not trusted: it cannot move the map's time past the
        moment ingest took the rows) nor later than the clock when the stamp itself is more
        than ``time_tolerance_s`` ahead of the wall clock (a forged entry, an ingest with
        a bad clock: counted ``time_clamped``, the clock does not move). The clock
        (``state.event_time``, saved with the table, so a restart does not take it back)
        is the largest event time of the entries applied so far.

        Replays give the map live processing gave, and so does the same traffic uploaded
        a day late in one bulk: the clock is a maximum of capture times, so it depends
        neither on when nor on how the entries were batched, only on their order and on
        which of them count; an honest entry's stamp is behind the matcher's wall clock
        (up to the hosts' clock skew, far below the tolerance) live and on every later
        replay, and its capture times are behind its stamp. What is given up: when one
        vehicle uploads a day late while others drive live, its rays are a day behind the
        clock, so they expire at the next sweep: they still meet the landmarks there and
        each other in their own unit, not rays of other passes (which is what the TTL
        means in event time)."""
        ahead = self.is_ahead(received_at)
        at, self.state.event_time = self.event_time(received_at, capture_t, ahead, self.now)
        if ahead:
            self.tally("time_clamped", 1)
        return at

    @staticmethod
    def event_time(
        received_at: float, capture_t: np.ndarray, ahead: bool, now: float
    ) -> tuple[float, float]:
        """:meth:`entry_time` without its effects: an entry's event time and the clock after
        it, from the clock ``now`` before it (``ahead``: its stamp is too far ahead)."""
        t = capture_t[np.isfinite(capture_t)]
        newest = float(t.max()) if t.size else received_at
        if ahead:
            return min(newest, received_at, now), now
        at = min(newest, received_at)
        return at, max(at, now)

    def note_trust(self, vehicle: str, t: VehicleTrust, ref: np.ndarray | None) -> None:
        """Keep (weight, offset chi2) of the vehicles stats show: downweighted or suspect."""
        w, c = t.weight(self.config.trust, ref), t.chi2(ref)
        if w < 1.0 or c > self.config.trust.chi2_gate:
            self.flagged[vehicle] = (w, c)
        else:
            self.flagged.pop(vehicle, None)

    def fleet_ref(self) -> np.ndarray | None:
        """The fleet's reference offset for the trust test (None while trust is off)."""
        if not self.config.trust.enabled:
            return None
        return self.fleet.reference()

    def area(self, tile: str) -> list[str]:
        """``tile`` and its 8 neighbours (cached: mercantile costs ~0.1 ms a call)."""
        a = self._areas.get(tile)
        if a is None:
            a = self._areas[tile] = [tile, *neighbours(tile)]
        return a

    def tile_of(self, x_ecef: np.ndarray) -> str:
        """The tile (at the service's zoom) an ECEF point is in."""
        lat, lon, _ = GEODESY.to_geodetic(x_ecef[None])
        return str(quadkeys_of(lat, lon, self.zoom)[0])


def facings_of(m: Matching, lms: list[Landmark]) -> Facing:
    """The landmarks' facings (:mod:`hdmap.mapping.facing`) from their view sums, their
    rays in the gating sums and, as independent looks, their passes.

    Pitfall: the view sum keeps the rays of a vehicle whose held passes were taken out of
    the sums (``TrustChanges`` action 2), so its length can exceed the ray count; the mean
    resultant length is clipped to 1 (spread 0) and the direction keeps those rays."""
    rows = np.array([lm.row for lm in lms], np.int64)
    view = np.array([lm.view for lm in lms], float).reshape(-1, 2)
    return facing_from_sums(
        view, m.sums.n_obs(rows), m.sums.n_passes(rows), m.config.gate.facing.min_rays
    )
