"""Durable stage logs between services: exactly-once hand-over over a lossy-in-theory bus.

Every stage output (ingest -> obs, matcher -> assoc, solver -> update) is a log in
the producer's SQLite. An entry is appended in the same transaction as the state
change that produced it, then published live on the stage key. Entries are
numbered per (producer, tile) by ``seq`` (1, 2, 3, ...) and per producer by
``gseq`` (global order).

A consumer records, in the same transaction as the state change an entry causes,
the last ``seq`` it applied per (producer, tile). It therefore

- drops an entry it has already applied (a live duplicate after a replay),
- buffers an entry that arrives ahead of a gap and asks for the missing ones,
- catches up on start, on a gap, when a producer (re)appears and periodically,
  by querying the producers' replay queryables (``hdmap/v1/log/<stage>/*/<region>``)
  with its offsets; replayed entries are applied in ``gseq`` order.

Gaps are bounded (:class:`GapPolicy`): at most ``max_ahead`` entries wait behind gaps
(more are dropped: the producer's log still has them); a gap the catch-up did not fill is
tried again after ``retry_s``, doubling, not at every batch; one still open after
``timeout_s`` is reported (counted, logged) and its waiting entries dropped, so that an
entry no producer wrote (a forged one far ahead) cannot hold anything up for long. The
buffer only saves a replay: what it drops is fetched again from the producer's log.

So nothing committed upstream is lost (it is in the producer's log until the
consumer has it) and nothing is applied twice (offsets commit with the effects).
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from hdmap.geo.tiles import in_region
from hdmap.runtime.log_policy import GapPolicy
from schemas import (
    DecodeError,
    ErrorReply,
    LogEntry,
    LogHead,
    LogMark,
    LogQuery,
    decode_replay,
    keys,
)

log = logging.getLogger(__name__)

STAGE_KEYS: dict[str, Callable[[str], str]] = {
    "obs": keys.obs,
    "assoc": keys.assoc,
    "update": keys.update,
}


@dataclass
class ConsumerStats:
    applied: int = 0
    duplicates: int = 0
    gaps: int = 0
    replayed: int = 0
    catchups: int = 0
    replay_refused: int = 0
    """Catch-up answers a producer refused (its log deleted below this consumer)."""
    resyncs: int = 0
    """Times a producer restored from an older state was met (a tile or its watermark)."""
    ahead_dropped: int = 0
    """Live entries not held behind a gap (the buffer was full); replayed later."""
    gaps_expired: int = 0
    """Gaps not filled within ``GapPolicy.timeout_s`` (their waiting entries dropped)."""
    checkpoints: int = 0
    """Producer checkpoints taken in place of deleted entries (``hdmap.runtime.log_checkpoint``)."""


LAG_CAP = 1_000_000


class LogConsumer:
    """Consumer side: in-order, exactly-once delivery of a stage's entries for a region.

    Invariant (the watermark): every entry of the region with ``gseq`` up to
    ``watermark[producer]`` is delivered, except in tiles where an entry waits behind a
    gap. A catch-up therefore lists only the tiles delivered past the watermark (to skip
    what it has) and the tiles with a gap (to fill them whatever their ``gseq``), and the
    producer's :class:`LogHead` moves the watermark up: the query grows with the tiles
    active since the last catch-up, not with every tile the region ever held. The
    watermark is saved only by a transaction that leaves nothing delivered uncommitted,
    so the saved one holds for the saved offsets.

    Invariant (epochs): a tile's offset and the epoch of the entry that set it are kept
    together, and so are a producer's watermark and the (epoch, ``gseq``) of its last
    entry delivered. An entry of an older run than its tile's is stale (dropped); one of a
    newer run whose ``base`` is below the tile's offset resynchronises the tile to
    ``base`` (the producer was restored from an older state; what was applied past it
    stays applied, once); a newer run that began (``gbase``) below the producer's last
    entry delivered takes the watermark back to ``gbase`` and the tiles past it are asked
    for by ``gseq`` (from an entry or the producer's :class:`LogHead`). Pitfall: a
    restored producer's entries that its consumers had not received when it was lost are
    lost with it; restore the consumers downstream too, or accept it (docs/operations.md).

    Pitfall: the watermark trusts the producer's :class:`LogHead`. A forged head (anyone
    may answer on ``hdmap/v1/log/**`` in default mode; in secured mode only services may)
    with a large ``through`` makes the consumer skip what it has not seen in tiles with no
    gap; an entry that arrives later in such a tile reveals the gap and it is filled
    then. The stage keys and replay queryables must be the services' alone (secured
    mode's ACL) wherever the bus is not trusted.
    """

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS offsets (
        stage TEXT NOT NULL, producer TEXT NOT NULL, tile TEXT NOT NULL, seq INTEGER NOT NULL,
        epoch INTEGER NOT NULL DEFAULT 0,
        PRIMARY KEY (stage, producer, tile)) WITHOUT ROWID;
    CREATE TABLE IF NOT EXISTS watermarks (
        stage TEXT NOT NULL, producer TEXT NOT NULL, gseq INTEGER NOT NULL,
        epoch INTEGER NOT NULL DEFAULT 0, top INTEGER NOT NULL DEFAULT 0,
        PRIMARY KEY (stage, producer)) WITHOUT ROWID;
    """

    def __init__(
        self,
        conn: sqlite3.Connection,
        stage: str,
        prefixes: Sequence[str],
        gaps: GapPolicy | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.stage = stage
        self.prefixes = list(prefixes)
        self.policy = gaps or GapPolicy()
        self.clock = clock
        self._conn = conn
        self._opened: dict[tuple[str, str], float] = {}
        """When each gap with entries waiting behind it opened (the consumer's clock)."""
        self._tries = 0
        """Catch-ups in a row that left a gap open (the retry delay doubles with them)."""
        self._retry_at: float | None = None
        self.more = False
        """The last catch-up round was cut short (``limit``): the next round is due now."""
        self.generation = 0
        """Bumped by every rewind: a catch-up asked before it is stale."""
        self._restarted_now: set[str] = set()
        """Producers met restored in the answer being absorbed (their heads are not taken)."""
        conn.executescript(self.SCHEMA)
        for table, col in (("offsets", "epoch"), ("watermarks", "epoch"), ("watermarks", "top")):
            if col not in {r[1] for r in conn.execute(f"PRAGMA table_info({table})")}:
                # a database from before epochs
                conn.execute(f"ALTER TABLE {table} ADD COLUMN {col} INTEGER NOT NULL DEFAULT 0")
        self._committed: dict[tuple[str, str], int] = {}
        self._committed_wm: dict[str, int] = {}
        self._ahead: dict[tuple[str, str], dict[int, LogEntry]] = defaultdict(dict)
        self._pending_commit: dict[tuple[str, str], int] = {}
        self._pending_epochs: dict[tuple[str, str], int] = {}
        self._pending_wm: dict[str, tuple[int, tuple[int, int]]] = {}
        self._seen: dict[tuple[str, str], int] = {}
        self.stats = ConsumerStats()
        self.cut: dict[str, int] | None = None
        """Set while a handover holds the consumer at one position of its producers' logs
        (:meth:`hold_at`): no entry past it is delivered."""
        self._rewind()

    def _rewind(self) -> None:
        """Back to the committed state (start, rollback)."""
        rows = self._conn.execute(
            "SELECT producer, tile, seq, epoch FROM offsets WHERE stage=?", (self.stage,)
        ).fetchall()
        self._committed = {(p, t): s for p, t, s, _e in rows}
        self._committed_epochs = {(p, t): e for p, t, _s, e in rows}
        marks = self._conn.execute(
            "SELECT producer, gseq, epoch, top FROM watermarks WHERE stage=?", (self.stage,)
        ).fetchall()
        self._committed_wm = {p: g for p, g, _e, _t in marks}
        self._committed_top = {p: (e, t) for p, _g, e, t in marks}
        self._delivered = dict(self._committed)
        self._epochs = dict(self._committed_epochs)
        """The epoch of each tile's last delivered entry."""
        self._watermark = dict(self._committed_wm)
        self._top = dict(self._committed_top)
        """Each producer's last entry delivered, as ``LogEntry.order`` (epoch, gseq)."""
        self._recent: dict[str, dict[str, tuple[int, int]]] = defaultdict(dict)
        """producer -> tile -> (delivered seq, its gseq) for deliveries past the watermark."""
        self._uncommitted: set[tuple[str, str]] = set()
        self._ahead.clear()
        self._opened.clear()
        self._pending_commit = {}
        self._pending_wm = {}
        self.need_catchup = True
        self.more = False
        self.generation += 1

    # -- delivery ---------------------------------------------------------------------

    def offer(self, entry: LogEntry) -> list[LogEntry]:
        """A live entry -> the entries now deliverable in order (maybe none, maybe several)."""
        if not in_region(entry.tile, self.prefixes) or self.past_cut(entry):
            return []
        k = (entry.producer, entry.tile)
        epoch = self._epochs.get(k, 0)
        if 0 < entry.epoch < epoch:  # from a run older than the one the tile is at (0: none)
            self.stats.duplicates += 1
            return []
        if entry.epoch > self._top.get(entry.producer, (0, 0))[0]:
            self._check_run(entry.producer, entry.epoch, entry.gbase)
        if entry.epoch > epoch and entry.base < self._delivered.get(k, 0):
            self._resync(k, entry)
        if entry.seq > self._seen.get(k, 0):
            self._seen[k] = entry.seq
        last = self._delivered.get(k, 0)
        if entry.seq <= last:
            self.stats.duplicates += 1
            self._note(entry, last)
            return []
        if entry.checkpoint:  # the tile's state as of its seq: stands for the entries before
            self.stats.checkpoints += 1
            last = entry.seq - 1
            for s in [s for s in self._ahead.get(k, {}) if s <= entry.seq]:
                del self._ahead[k][s]
        if entry.seq > last + 1:
            self._hold(k, entry)
            return []
        out = [entry]
        buf = self._ahead.get(k)
        while buf and (nxt := buf.pop(out[-1].seq + 1, None)) is not None:
            out.append(nxt)
        if buf is not None and not buf:
            del self._ahead[k]
            self._opened.pop(k, None)
        self._delivered[k] = out[-1].seq
        self._epochs[k] = max(e.epoch for e in out)
        self._top[k[0]] = max(self._top.get(k[0], (0, 0)), *(e.order for e in out))
        self._uncommitted.add(k)
        self._note(out[-1], out[-1].seq)
        return out

    # -- a cut (a handover joining regions) -------------------------------------------------

    def hold_at(self, cut: dict[str, int] | None) -> None:
        """Deliver entries up to ``cut`` (producer -> ``gseq``; a producer not named: none)
        and none past it, or every entry again (None). Entries past the cut are not
        delivered (a replay and live traffic alike: they stay in their producer's log),
        and a producer's watermark stops at its cut, so catch-ups go on until the region's
        entries up to the cut are delivered (:meth:`at_cut`). A catch-up follows."""
        self.cut = None if cut is None else dict(cut)
        self.need_catchup = True

    def past_cut(self, entry: LogEntry) -> bool:
        return self.cut is not None and entry.gseq > self.cut.get(entry.producer, 0)

    def at_cut(self) -> bool:
        """Held at a cut, with what was delivered committed and, per producer named, the
        region's entries up to its cut delivered (the committed watermark is there) or the
        entry at the cut itself (this consumer was the one furthest in that log: it is no
        less complete than it was when it stopped; a producer that has gone away answers
        no catch-up)."""
        if self.cut is None or self._uncommitted:
            return False
        top = self.positions()
        return all(
            max(self._committed_wm.get(p, 0), top.get(p, 0)) >= g for p, g in self.cut.items()
        )

    def positions(self) -> dict[str, int]:
        """Per producer, the ``gseq`` of the last entry delivered from its current run
        (what an instance that is not applying has applied; its input position)."""
        return {p: g for p, (_e, g) in self._top.items() if g > 0}

    def _resync(self, k: tuple[str, str], entry: LogEntry) -> None:
        """The producer's run of ``entry`` began below what this consumer has of the tile:
        it was restored from an older state, and what the consumer applied past ``base``
        is not in its log (it stays applied). The tile goes on from ``base``."""
        log.warning(
            "%s: producer %s restarted from an older state (epoch %d): tile %s goes on from "
            "seq %d (had %d)",
            self.stage,
            k[0],
            entry.epoch,
            k[1],
            entry.base,
            self._delivered.get(k, 0),
        )
        self.stats.resyncs += 1
        self._delivered[k] = entry.base
        self._committed[k] = min(self._committed.get(k, 0), entry.base)
        self._epochs[k] = entry.epoch
        self._seen[k] = entry.base
        self._ahead.pop(k, None)
        self._opened.pop(k, None)
        self._recent.get(k[0], {}).pop(k[1], None)

    def _hold(self, k: tuple[str, str], entry: LogEntry) -> None:
        """Keep a live entry behind its tile's gap (if the buffer has room); a new gap asks
        for a catch-up at once."""
        self.stats.gaps += 1
        if self.ahead_entries >= self.policy.max_ahead:
            self.stats.ahead_dropped += 1
            self.need_catchup = True
            return
        if k not in self._opened:
            self._opened[k] = self.clock()
            self.need_catchup = True
        self._ahead[k][entry.seq] = entry

    @property
    def gaps_open(self) -> int:
        """Tiles with live entries waiting behind a gap."""
        return len(self._opened)

    @property
    def ahead_entries(self) -> int:
        """Live entries waiting behind gaps."""
        return sum(len(b) for b in self._ahead.values())

    def oldest_gap_s(self, now: float | None = None) -> float:
        """Seconds the oldest open gap has been open (0: none)."""
        if not self._opened:
            return 0.0
        return max(0.0, (self.clock() if now is None else now) - min(self._opened.values()))

    def marks(self, consumer: str) -> list[LogMark]:
        """How far this consumer (instance ``consumer``) has applied each producer's log:
        its committed watermark, in the run of the last entry it applied; none for a
        producer with a gap open (its watermark does not cover the tile that waits)."""
        gapped = {p for p, _t in self._ahead}
        return [
            LogMark(self.stage, p, consumer, g, self._committed_top.get(p, (0, 0))[0])
            for p, g in sorted(self._committed_wm.items())
            if g > 0 and p not in gapped
        ]

    def wants_catchup(self, now: float) -> bool:
        """Whether a catch-up is due at ``now``: asked for (start, a new gap, a producer
        appearing, the periodic timer, a rollback), the rest of a cut-short one, or the
        retry of a gap the last one left open."""
        if self.need_catchup or self.more:
            return True
        return bool(self._ahead) and self._retry_at is not None and now >= self._retry_at

    def begin_catchup(self) -> None:
        """A catch-up starts: what asked for it is served by it."""
        self.stats.catchups += 1
        self.need_catchup = False

    def end_round(self, complete: bool, now: float) -> None:
        """A catch-up round was absorbed: another at once if it was cut short; a gap still
        open is tried again after the policy's delay (doubling), not at every batch."""
        self.more = not complete
        if self.more:
            return
        if not self._ahead:
            self._tries, self._retry_at = 0, None
            return
        delay = min(self.policy.retry_max_s, self.policy.retry_s * 2.0**self._tries)
        self._tries += 1
        self._retry_at = now + delay

    def expire_gaps(self, now: float) -> list[tuple[str, str, int, int]]:
        """Drop the entries waiting behind gaps open ``timeout_s`` or longer: each such gap
        as (producer, tile, last delivered seq, first waiting seq)."""
        out = []
        for k, t0 in list(self._opened.items()):
            if now - t0 < self.policy.timeout_s:
                continue
            buf = self._ahead.pop(k, {})
            del self._opened[k]
            self._seen[k] = self._delivered.get(k, 0)  # a forged seq claims no lag
            out.append((k[0], k[1], self._delivered.get(k, 0), min(buf, default=0)))
            self.stats.gaps_expired += 1
        return out

    def _note(self, entry: LogEntry, delivered: int) -> None:
        """Remember a tile delivered past the watermark, so catch-ups skip what it has."""
        if entry.gseq > self._watermark.get(entry.producer, 0):
            mine = self._recent[entry.producer]
            if entry.gseq > mine.get(entry.tile, (0, 0))[1]:
                mine[entry.tile] = (delivered, entry.gseq)

    def record(self, entries: Iterable[LogEntry]) -> None:
        """Write offsets for applied entries (inside the caller's transaction), and the
        watermarks if this transaction leaves nothing delivered uncommitted."""
        last: dict[tuple[str, str], tuple[int, int]] = {}
        for e in entries:
            k = (e.producer, e.tile)
            last[k] = max(last.get(k, (0, 0)), (e.epoch, e.seq))
        self._conn.executemany(
            "INSERT OR REPLACE INTO offsets(stage, producer, tile, seq, epoch) "
            "VALUES (?, ?, ?, ?, ?)",
            [(self.stage, p, t, s, ep) for (p, t), (ep, s) in last.items()],
        )
        latest = {k: s for k, (_ep, s) in last.items()}
        self._pending_commit.update(latest)
        self._pending_epochs.update({k: ep for k, (ep, _s) in last.items()})
        done = self._committed
        self._uncommitted = {k for k in self._uncommitted if done.get(k, 0) < self._delivered[k]}
        if all(latest.get(k, 0) >= self._delivered[k] for k in self._uncommitted):
            moved = {
                p: (self._watermark.get(p, 0), self._top.get(p, (0, 0)))
                for p in set(self._watermark) | set(self._top)
                if (self._watermark.get(p, 0), self._top.get(p, (0, 0)))
                != (self._committed_wm.get(p, 0), self._committed_top.get(p, (0, 0)))
            }
            self._conn.executemany(
                "INSERT OR REPLACE INTO watermarks(stage, producer, gseq, epoch, top) "
                "VALUES (?, ?, ?, ?, ?)",
                [(self.stage, p, w, t[0], t[1]) for p, (w, t) in moved.items()],
            )
            self._pending_wm = moved

    def on_commit(self) -> None:
        self.stats.applied += sum(
            max(0, s - self._committed.get(k, 0)) for k, s in self._pending_commit.items()
        )
        self._committed.update(self._pending_commit)
        self._committed_epochs.update(self._pending_epochs)
        self._committed_wm.update({p: w for p, (w, _r) in self._pending_wm.items()})
        self._committed_top.update({p: t for p, (_w, t) in self._pending_wm.items()})
        for k, seq in self._pending_commit.items():
            if seq > self._delivered.get(k, 0):  # entries re-applied after a rollback
                self._delivered[k] = seq
            if seq >= self._delivered.get(k, 0):
                self._uncommitted.discard(k)
        self._pending_commit = {}
        self._pending_epochs = {}
        self._pending_wm = {}

    def on_rollback(self) -> None:
        """What was delivered but not committed will come again: rewind and catch up."""
        self._rewind()

    # -- catch-up ---------------------------------------------------------------------

    def selector(self) -> list[str]:
        stage_key = f"{keys.ROOT}/log/{self.stage}/*"
        return [f"{stage_key}/{keys.region(p)}" for p in (self.prefixes or [""])]

    def query(self, limit: int) -> LogQuery:
        """What a catch-up asks: the tiles delivered past the watermark and those with a
        gap, by seq; the rest of the region after the watermarks."""
        listed = {p: {t: s for t, (s, _g) in tiles.items()} for p, tiles in self._recent.items()}
        for p, t in self._ahead:
            listed.setdefault(p, {})[t] = self._delivered.get((p, t), 0)
        return LogQuery(self.stage, listed, self.prefixes, limit, dict(self._watermark))

    def absorb(self, replies: Iterable[bytes]) -> tuple[list[LogEntry], bool]:
        """One round's replies -> (entries now deliverable, whether every producer that
        answered sent all it had). Entries are offered in each producer's ``gseq`` order;
        each producer's :class:`LogHead` then raises its watermark."""
        got: list[LogEntry] = []
        heads: dict[str, LogHead] = {}
        for data in replies:
            try:
                r = decode_replay(data)
            except DecodeError:
                self._refused(data)
                continue
            if isinstance(r, LogEntry):
                got.append(r)
            elif r.stage == self.stage and (
                r.producer not in heads or r.through < heads[r.producer].through
            ):
                heads[r.producer] = r
        got.sort(key=lambda e: (e.producer, e.order))
        self._restarted_now: set[str] = set()
        out: list[LogEntry] = []
        for e in got:
            delivered = self.offer(e)
            self.stats.replayed += len(delivered)
            out += delivered
        complete = True
        for p, h in heads.items():
            if p in self._restarted_now or self._restored(h):
                complete = False  # asked again from the lowered watermark
                continue
            self._advance(p, h.through)
            held = self.cut is not None and self._watermark.get(p, 0) >= self.cut.get(p, 0)
            complete = complete and (h.complete or held)  # what is past a cut is not wanted
        return out, complete

    def _refused(self, data: bytes) -> None:
        """A reply that is not an entry nor a head: a producer's refusal (counted and
        logged: a log truncated below this consumer needs an operator), or garbage."""
        try:
            err = ErrorReply.from_bytes(data)
        except DecodeError:
            log.warning("undecodable replay reply ignored")
            return
        self.stats.replay_refused += 1
        log.error("%s: catch-up refused: %s: %s", self.stage, err.field, err.reason)

    def _restored(self, h: LogHead) -> bool:
        """Whether ``h`` shows its producer restored from an older state
        (:meth:`_check_run` on its first run newer than the last entry delivered)."""
        top = self._top.get(h.producer, (0, 0))[0]
        newer = [(e, g) for e, g in h.epochs if e > top]
        return bool(newer) and self._check_run(h.producer, *newer[0])

    def _check_run(self, producer: str, epoch: int, gbase: int) -> bool:
        """The producer has a run ``epoch`` newer than the last entry delivered from it,
        begun after its ``gseq`` ``gbase``. If that entry's ``gseq`` is past ``gbase`` it
        was not written before the run began: it is from a run the producer lost (it was
        restored from an older state), and the new run numbers its entries like the lost
        ones. The watermark then goes back to ``gbase`` and the tiles past it are asked
        for by ``gseq``, so that every entry of the new run is met (each tile resyncs on
        its first, :meth:`_resync`). Whether it was so."""
        top = self._top.get(producer, (0, 0))
        if top[1] <= gbase:
            return False
        log.warning(
            "%s: producer %s restarted from an older state (its run %d began after gseq %d, "
            "this consumer had up to %d): asking again from there",
            self.stage,
            producer,
            epoch,
            gbase,
            top[1],
        )
        self.stats.resyncs += 1
        self._restarted_now.add(producer)
        self._top[producer] = (epoch, gbase)
        self._watermark[producer] = min(self._watermark.get(producer, 0), gbase)
        self._recent.pop(producer, None)
        self.need_catchup = True
        return True

    def _advance(self, producer: str, through: int) -> None:
        """The producer's answer is delivered up to ``through``: raise its watermark there,
        below any entry still waiting behind a gap (its missing ones are below it), and not
        past a cut (:meth:`hold_at`: the entries past it were not delivered)."""
        if self.cut is not None:
            through = min(through, self.cut.get(producer, 0))
        waiting = [
            min(buf.values(), key=lambda e: e.gseq).gseq - 1
            for (p, _t), buf in self._ahead.items()
            if p == producer and buf
        ]
        w = min([through, *waiting])
        if w <= self._watermark.get(producer, 0):
            return
        self._watermark[producer] = w
        mine = self._recent.get(producer, {})
        for t in [t for t, (_s, g) in mine.items() if g <= w]:
            del mine[t]

    @property
    def lag(self) -> int:
        """Entries seen from producers (live or replayed) but not applied yet (each
        (producer, tile) counts at most ``LAG_CAP``: a forged entry can claim any seq)."""
        return sum(
            min(max(0, s - self._committed.get(k, 0)), LAG_CAP) for k, s in list(self._seen.items())
        )

    def committed(self, producer: str, tile: str) -> int:
        """The last seq applied and committed for (producer, tile)."""
        return self._committed.get((producer, tile), 0)

    @property
    def offsets(self) -> dict[tuple[str, str], int]:
        return dict(self._committed)

    @property
    def marks_behind(self) -> bool:
        """A catch-up raised a watermark that no transaction has committed yet (nothing to
        apply came with it): :meth:`record` with no entries commits it."""
        return not self._uncommitted and any(
            (self._watermark.get(p, 0), self._top.get(p, (0, 0)))
            != (self._committed_wm.get(p, 0), self._committed_top.get(p, (0, 0)))
            for p in set(self._watermark) | set(self._top)
        )

    @property
    def watermarks(self) -> dict[str, int]:
        """Committed watermarks per producer."""
        return dict(self._committed_wm)
