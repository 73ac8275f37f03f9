"""Matcher: the single writer of landmark identities for its region.

Per batch of obs entries (one upload's rays for one tile each, in order; see
:mod:`hdmap.runtime.stage`): each entry's event time (its capture times, clamped by its
ingest stamp) moves the matcher's clock
(:meth:`hdmap.mapping.matching.Matching.entry_time`: monotone, an entry stamped far ahead
of the wall clock does not move it), the entry joins the gating tick of its event time
(:func:`hdmap.mapping.tick.enter`: the tick before it may end), it is handed to the domain
(:func:`hdmap.mapping.unit.match_unit`: association, linking, pending pool, initiation,
probation, merge), and what the clock's advance settles follows
(:func:`hdmap.mapping.event_time.advance`: vehicles on probation that stopped driving are
let go, trust records of vehicles gone for long are forgotten, and once per minute of
event time old pending rays expire and quiet passes close); then one
:class:`schemas.AssocGroup` per landmark home tile goes to the assoc log, and the state
(with the clock) is saved in the same transaction. No timer changes the map: the wall
clock only refuses ingest stamps far ahead of it.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hdmap.mapping import presence
from hdmap.mapping.estimator import LandmarkSums
from hdmap.mapping.estimator.solve import preload
from hdmap.mapping.event_time import advance
from hdmap.mapping.matching import AssocOutput, Matching, MatchingConfig, new_output
from hdmap.mapping.tick import enter, tick_of
from hdmap.mapping.unit import (
    Checked,
    Prepared,
    associate_prepared,
    match_unit,
    prepare_unit,
    prepare_units,
    signature,
)
from hdmap.runtime.config import ConfigError
from hdmap.runtime.service import ServiceOptions
from hdmap.runtime.stage import StageService
from schemas import (
    DROP,
    RELEASE,
    AssocGroup,
    DecodeError,
    ExistenceRows,
    Links,
    LogEntry,
    NewLandmarks,
    Observations,
    ObsGroup,
    TrustChanges,
)
from schemas.ids import pass_key
from services.matcher import held_links
from services.matcher.state import MatcherState

log = logging.getLogger(__name__)

Associated = tuple[Prepared, Checked | None]
"""A unit prepared for association and its association (None: no candidate)."""


@dataclass(frozen=True)
class MatcherConfig(MatchingConfig):
    """The matcher's configuration (:class:`~hdmap.mapping.matching.MatchingConfig`),
    checked as it is loaded."""

    associate_ahead: int = 32
    """Most units of one gating tick associated in one call (the unit that starts a run
    and those after it in the batch the tick will hold): the work of a call grows with
    its units' pairs. Any size gives the same map (each unit's association is its own)."""

    def __post_init__(self) -> None:
        budgets = ("pending_max_per_pass", "pending_max_per_vehicle", "quarantine_after")
        for name in (*budgets, "init_reseed_max"):
            if getattr(self, name) < 0:
                raise ConfigError(
                    f"matcher.{name}: must be >= 0 (0: off), got {getattr(self, name)}"
                )
        if self.associate_ahead < 1:
            raise ConfigError(f"matcher.associate_ahead: must be >= 1, got {self.associate_ahead}")
        if 0 < self.pending_max_per_pass < self.init.min_rays:
            raise ConfigError(
                f"matcher.pending_max_per_pass: below init.min_rays ({self.init.min_rays}), got "
                f"{self.pending_max_per_pass} (no pass could start a landmark); 0 is no limit"
            )
        if not self.time_tolerance_s > 0:
            raise ConfigError(
                f"matcher.time_tolerance_s: must be > 0, got {self.time_tolerance_s} (no "
                "entry stamped by an ingest whose clock is a little ahead would count)"
            )
        forget = self.trust.forget_after_s
        if 0 < forget <= self.trust.probation_ttl_s:
            raise ConfigError(
                "matcher.trust.forget_after_s: must exceed probation_ttl_s "
                f"({self.trust.probation_ttl_s}), got {forget} (a vehicle on probation would "
                "be forgotten with its passes held); 0 keeps records for ever"
            )
        if not self.sweep_every_s > 0:
            raise ConfigError(
                f"matcher.sweep_every_s: must be > 0, got {self.sweep_every_s} (pending rays "
                "would never expire, passes never close)"
            )
        if 0 < self.close_passes_after_s <= self.pending_ttl_s:
            raise ConfigError(
                "matcher.close_passes_after_s: must exceed pending_ttl_s "
                f"({self.pending_ttl_s}), got {self.close_passes_after_s} (a pending ray of a "
                "closed pass would start a new cluster); 0 keeps passes open"
            )


def _capture_times(g: ObsGroup) -> np.ndarray:
    """An obs entry's capture times: its rays' and its absences' (an entry of absences
    alone moves the clock by their times, not by its ingest stamp)."""
    if not len(g.absences):
        return np.asarray(g.obs.t, float)
    return np.r_[np.asarray(g.obs.t, float), np.asarray(g.absences.t, float)]


def wall_clock() -> float:
    """Wall-clock seconds (only to refuse ingest stamps far ahead of it)."""
    return time.time()


def assoc_body(out: AssocOutput) -> bytes:
    """One home tile's output of an obs entry as an encoded :class:`AssocGroup`."""
    links = np.array(out.links, dtype=np.uint64).reshape(-1, 3)
    created = out.created
    retired = np.array(out.retired, np.uint64).reshape(-1, 2)
    return AssocGroup(
        vehicles=out.vehicles,
        links=Links(
            links[:, 0],
            links[:, 1].astype(np.uint32),
            links[:, 2],
            np.array(out.received_at, float),
            np.array(out.weight, np.float32),
        ),
        obs=Observations.concat(out.obs),
        created=NewLandmarks(
            id=np.array([c[0] for c in created], np.uint64),
            sign_class=np.array([c[1] for c in created], np.uint16),
            lat=np.array([c[2] for c in created], float),
            lon=np.array([c[3] for c in created], float),
            h=np.array([c[4] for c in created], float),
        ),
        retired=np.r_[retired[:, 0], np.array(out.ended, np.uint64)],
        existence=existence_rows(out),
        merged_into=retired[:, 1].copy(),
        held=np.array(out.held, bool),
        trust=TrustChanges(
            np.array([c[0] for c in out.trust], np.uint32),
            np.array([DROP if c[1] else RELEASE for c in out.trust], np.uint8),
            np.array([c[2] for c in out.trust], np.float32),
        ),
    ).to_bytes()


def existence_rows(out: AssocOutput) -> ExistenceRows:
    """The output's existence changes as the wire table (by id)."""
    rows = [out.existence[i] for i in sorted(out.existence)]
    return ExistenceRows(
        landmark_id=np.array([r[0] for r in rows], np.uint64),
        p_exist=np.array([r[1] for r in rows], np.float32),
        state=np.array([r[2] for r in rows], np.uint8),
        first_seen=np.array([r[3] for r in rows], float),
        last_seen=np.array([r[4] for r in rows], float),
    )


class MatcherService(StageService):
    """Orchestration of the matcher: obs entries in, the domain's steps
    (:class:`~hdmap.mapping.matching.Matching`), assoc entries and counters out, the state
    saved in each transaction."""

    name = "matcher"
    input_stage = "obs"
    upstream = "ingest"
    output_stage = "assoc"
    hands_over = True

    def __init__(self, opts: ServiceOptions, config: MatcherConfig | None = None):
        super().__init__(opts)
        self.config = config or MatcherConfig()
        self.state = MatcherState(self.db)
        self.matching = Matching(
            self.config, self.state, self.opts.zoom, self.region, self.count, wall_clock
        )
        self.frames = self.matching.frames
        self._ahead_of: dict[int, tuple[int, Associated]] = {}
        """Units of the current batch associated ahead, by index: (the tick serial they were
        associated in, the unit and its association)."""
        self._reload()
        preload()  # scipy.stats for the covariance inflation, not in the first batch
        self._counts: dict[str, float] = {}
        self._snapshot_counts()

    # -- the domain's state, as the service's ------------------------------------------------

    @property
    def sums(self) -> LandmarkSums:
        """The gating sums."""
        return self.matching.sums

    # -- transaction participants: on failure, memory is rebuilt from the database --------

    def _reload(self) -> None:
        """Rebuild the memory (state, gating sums, open passes, fleet) from the database."""
        sums = LandmarkSums(self.config.estimator)
        self.state.load(sums.unpack_rows)
        self.matching.restart(sums)
        row_of = {lid: lm.row for lid, lm in self.state.landmarks.items()}
        self.matching.hold_again(held_links.load(self.db, row_of))

    def on_commit(self) -> None:
        """Nothing to do: memory already is what was committed."""

    def on_rollback(self) -> None:
        """Memory may hold the failed transaction's changes: rebuild it."""
        self._reload()

    def participants(self) -> list:
        """The service itself takes part in each transaction (for its rollback)."""
        return [self]

    def setup(self) -> None:
        """The base service's setup, and the stats counts refreshed every minute (expiry
        runs on event time, in :meth:`apply`)."""
        super().setup()
        self.every(60.0, lambda _now: self._snapshot_counts())

    # -- apply -----------------------------------------------------------------------------

    def apply(self, entries: list[LogEntry]) -> None:
        """Decode each entry, move the clock, match its unit and settle what the clock's
        advance settles (:func:`hdmap.mapping.event_time.advance`: probation, expiry, pass
        closing); after each entry, emit one assoc entry per home tile it touched; save.

        The units that will share a gating tick are associated together when the first of
        them comes (:meth:`_associate_ahead`); each is then checked to be what it was
        (:func:`hdmap.mapping.unit.signature`) before its association is used, and is
        associated alone if not.

        Invariant: the assoc log holds the same groups in the same order however the obs
        entries were batched (one per entry and home tile), so the solver, whose clock
        and pass closing follow its groups, builds the same map from uploads sent paced or
        in bulk. Pitfall: one group per batch (as it was) let a bulk catch-up put several
        uploads' rays in one group: the solver's clock jumped to the latest of them before
        the earliest were noted, its passes closed at other entries, and a late ray of a
        pass joined it in one run and started a new cluster in the other."""
        decoded: list[tuple[LogEntry, ObsGroup]] = []
        for e in entries:
            try:
                decoded.append((e, ObsGroup.from_bytes(e.body)))
            except DecodeError as exc:
                self.reject(f"obs.{exc.field}")
        self.metrics.ages(g.received_at for _e, g in decoded)
        ahead = [self.matching.is_ahead(g.received_at) for _e, g in decoded]
        self._ahead_of = {}
        for i, (e, g) in enumerate(decoded):
            self.matching.out = new_output()
            self._unit(e.tile, g, i, lambda i=i: self._associate_ahead(i, decoded, ahead))
            advance(self.matching)
            for home, out in sorted(self.matching.out.items()):
                self.emit(home, assoc_body(out))
        self._ahead_of = {}
        late = [g.received_at for (_e, g), a in zip(decoded, ahead, strict=True) if a]
        if late:
            log.warning(
                "%d obs entries stamped more than time_tolerance_s ahead of the matcher's "
                "wall clock (up to %.0f s past its event-time clock); their time not taken",
                len(late),
                max(late) - self.matching.now,
            )
        self._save()
        self.count("sums_rows_dropped", self.matching.compact_rows())

    def _save(self) -> None:
        """Write the held links and what changed (inside the transaction)."""
        held_links.save(self.db, *self.matching.held_to_save())
        self.state.save(self.matching.sums_as_held.pack_rows)

    def before_handover(self) -> None:
        """The held links go into the sums and the rows they touched are written: the
        database is then the whole state (a handover's checkpoint)."""
        self.matching.flush_links()
        self._save()

    # -- single domain steps (each as ``apply`` runs it) -------------------------------------

    def _unit(
        self,
        tile: str,
        g: ObsGroup,
        index: int = 0,
        batch: Callable[[], list[tuple[int, Associated]]] | None = None,
    ) -> float:
        """One decoded unit through the domain, at its event time on the matcher's clock
        (returned). Its association is the one ``batch()`` made for it earlier in its tick
        if it is still its own (:func:`hdmap.mapping.unit.signature`); else, when nothing
        was associated ahead, ``batch()`` associates it with the units after it in its
        tick; else it is associated alone."""
        m = self.matching
        at = m.entry_time(g.received_at, _capture_times(g))
        enter(m, at)  # the unit's gating tick (the one before it may end)
        if len(g.obs):
            self._match(tile, g, at, index, batch)
        if len(g.absences):
            t = m.state.trust_of(g.vehicle_id)
            held = t.held(m.config.trust)
            key = pass_key(g.vehicle_id, g.pass_id, held)
            presence.not_seen(m, g.vehicle_id, g.pass_id, key, g.absences, held)
        return at

    def _match(
        self,
        tile: str,
        g: ObsGroup,
        at: float,
        index: int,
        batch: Callable[[], list[tuple[int, Associated]]] | None,
    ) -> None:
        """The unit's rays associated and linked (:meth:`_unit`)."""
        m = self.matching
        u: Prepared | None = None
        res: Checked | None = None
        hit = self._ahead_of.pop(index, None)
        stale = hit is not None and hit[0] != m.tick_serial  # a tick ended in between
        if hit is not None and not stale:
            p, r = hit[1]
            if p.signature == signature(m, tile, g.vehicle_id):
                u, res = p, r
                self.count("assoc_ahead", 1)
            else:  # its vehicle's correction moved, a settlement emptied a landmark, ...
                self.count("assoc_redone", 1)
        elif batch is not None and m.config.tick_s > 0:
            if stale:  # a pass over its budget split the tick: associate again from here
                self.count("assoc_redone", 1)
            (_i, (u, res)), *later = batch()
            self._ahead_of = {k: (m.tick_serial, a) for k, a in later}
        if u is None:
            u = prepare_unit(m, tile, g.vehicle_id, g.pass_id, g.obs)
        match_unit(m, u, at, g.received_at, res)

    def _associate_ahead(
        self, i: int, decoded: list[tuple[LogEntry, ObsGroup]], ahead: list[bool]
    ) -> list[tuple[int, Associated]]:
        """Unit ``i`` (its clock moved) and the units after it in the batch that its tick
        will hold (their clock predicted: :meth:`Matching.event_time`; at most
        ``associate_ahead``), prepared and associated together."""
        m = self.matching
        now, tick = m.now, m.state.tick_id
        run = [i]
        for k in range(i + 1, min(len(decoded), i + self.config.associate_ahead)):
            g = decoded[k][1]
            at, now = m.event_time(g.received_at, _capture_times(g), ahead[k], now)
            if tick_of(m, at, now) != tick:
                break
            if len(g.obs):  # an entry of absences alone has no unit to associate
                run.append(k)
        units = prepare_units(
            m, [(e.tile, g.vehicle_id, g.pass_id, g.obs) for e, g in (decoded[k] for k in run)]
        )
        return list(zip(run, zip(units, associate_prepared(m, units), strict=True), strict=True))

    # -- timers and stats -----------------------------------------------------------------------

    def after_commit(self) -> None:
        """Refresh the stats counts after each committed batch."""
        self._snapshot_counts()

    def _snapshot_counts(self) -> None:
        """Counts for the stats thread, taken on the worker thread."""
        self._counts = {
            "landmarks": len(self.state.landmarks),
            "pending": self.state.pending_count(),
        }
        held = sorted(b.vehicle for b in self.state.passes.values() if b.quarantined)
        self._counts["passes_in_quarantine"] = len(held)
        by_vehicle = Counter(held)
        for v, k in sorted(by_vehicle.items(), key=lambda vk: (-vk[1], vk[0]))[:20]:
            self._counts[f"quarantine.{v}"] = k  # the 20 with the most, by name
        low = sorted((w, v) for v, (w, _c) in self.matching.flagged.items() if w < 1.0)
        self._counts["vehicles_downweighted"] = len(low)
        for w, v in low[:20]:  # the 20 least trusted, by name
            self._counts[f"weight.{v}"] = round(w, 6)
        gate = self.config.trust.chi2_gate
        odd = sorted((c, v) for v, (_w, c) in self.matching.flagged.items() if c > gate)
        for c, v in odd[-5:]:  # the 5 most consistent offsets (whether or not trust is on)
            self._counts[f"offset_chi2.{v}"] = round(c, 2)

    def extra_counters(self) -> dict[str, float]:
        """The base service's counters and the last stats counts."""
        out = super().extra_counters()
        out.update(self._counts)
        return out
