"""A stage service's side of handing its region over (``hdmap region split`` / ``merge``,
:mod:`hdmap.ops.region`): pause, report, hand out a checkpoint, stop.

On ``hdmap/v1/handover/<service>/<region>`` (:func:`schemas.keys.handover`) the worker
answers :class:`schemas.HandoverRequest`:

- ``pause``: at a batch boundary, the service's ``before_handover`` hook runs in one
  transaction (the matcher adds its held links to its sums, so the database alone is its
  state), the database is copied (SQLite's backup API) to ``handover.sqlite`` in the data
  dir, and from then on no input entry is applied: live entries are dropped (their
  producer's log keeps them for whoever takes the region over) and no catch-up runs. The
  service still serves its own log and takes its consumers' marks, so they drain it; its
  own marks on its producers' logs stay where they were.
- ``cut`` (paused only; regions being joined): apply the region's input entries up to
  the given position of every producer's log (``gseq``; a producer not named: none of
  its entries), none past it, then hold there: ``before_handover`` runs again and the
  checkpoint is taken anew (``at_cut`` in the reply). A cut below an entry the instance
  has applied is refused (field ``cut``); ``state`` and ``stop`` wait for the cut.
- ``status``: paused or not, the output log's head and the consumers' marks (from
  ``log_marks``, with their age), the input position (per producer, the last ``gseq``
  applied) and whether it holds at a cut.
- ``state``: ``CHUNK_BYTES`` of the checkpoint from ``offset`` (paused only).
- ``resume``: the handover is called off; the service applies its input again (a
  catch-up fetches what it dropped while paused). It also resumes by itself when no
  request has come for :data:`LEASE_S` (the tool died half-way).
- ``stop``: the process exits (after answering), telling its producers it has left
  (a mark at ``gseq`` 0: it no longer holds their logs; the instances that took its
  region over mark for themselves).

Invariant: the checkpoint is the state after the last transaction before the pause (or
the cut) and nothing is applied after it, so an instance started from it and from the
producers' logs after its offsets neither loses nor applies twice an entry. A bad request
is answered with an :class:`schemas.ErrorReply` naming the field and counted
(``rejected[handover.<field>]``).
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from hdmap.runtime.service import Item
from schemas import DecodeError, ErrorReply, HandoverReply, HandoverRequest, keys
from schemas.handover import CHUNK_BYTES

log = logging.getLogger(__name__)

CHECKPOINT = "handover.sqlite"
"""The checkpoint's file name in the data dir."""
LEASE_S = 300.0
"""A paused instance resumes by itself when no handover request has come for this long
(the tool died half-way): a region is never left stalled. The tool asks every half
second while it waits; cutting a checkpoint takes seconds per 100 MB."""


class Handover:
    """The pause flag and the checkpoint of one stage service (worker thread only)."""

    def __init__(
        self,
        name: str,
        instance: str,
        region_label: str,
        db: sqlite3.Connection,
        data_dir: Path,
        head: Callable[[], int],
        clock: Callable[[], float] = time.monotonic,
        inputs: Callable[[], dict[str, int]] = dict,
        hold: Callable[[dict[str, int] | None], None] = lambda _cut: None,
    ):
        self.name, self.instance, self.region_label = name, instance, region_label
        self.db = db
        self.path = Path(data_dir) / CHECKPOINT
        self.head = head
        """The output log's last ``gseq`` (0: no output log)."""
        self.paused = False
        self.clock = clock
        self.asked_at = 0.0
        """When the last handover request came (the pause's lease)."""
        self.stop: threading.Event | None = None
        """Set by ``stop`` (the service's run loop watches it)."""
        self.inputs = inputs
        """Per producer of the input, the last ``gseq`` applied."""
        self.hold = hold
        """Holds the input at a cut (None: lets it go)."""
        self.cut: dict[str, int] | None = None
        self.at_cut = False
        """The input up to :attr:`cut` is applied and checkpointed."""

    @property
    def advancing(self) -> bool:
        """Paused, applying its input up to a cut it has not reached yet."""
        return self.paused and self.cut is not None and not self.at_cut

    @property
    def applying(self) -> bool:
        """Whether input entries are applied (not paused, or paused and advancing)."""
        return not self.paused or self.advancing

    def reach_cut(self, prepare: Callable[[], None]) -> None:
        """The input is applied up to the cut: make the database whole and checkpoint it."""
        prepare()
        self._checkpoint()
        self.at_cut = True
        log.info("%s %s: holds at the cut %s (log head %d)", self.name, self.instance,
                 self.cut, self.head())  # fmt: skip

    def key(self) -> str:
        return keys.handover(self.name, self.region_label)

    def answer(self, it: Item, prepare: Callable[[], None], reject: Callable[[str], None]) -> None:
        """Serve one request (``prepare``: the service's ``before_handover`` in a
        transaction; ``reject``: count a refused request by field)."""
        q = it.query
        if q is None:
            return
        self.asked_at = self.clock()
        req: HandoverRequest | None = None
        try:
            req = HandoverRequest.from_bytes(it.payload)
            out, err = self._serve(req, prepare).to_bytes(), None
        except DecodeError as exc:
            reject(f"handover.{exc.field}")
            out, err = None, ErrorReply.of(exc).to_bytes()
        try:
            if err is None:
                q.reply(q.key_expr, out)
            else:
                q.reply_err(err)
        except zenoh.ZError as exc:  # the tool is gone: nothing to tell
            log.warning("%s: handover reply not sent: %s", self.name, exc)
        finally:
            q.drop()
        if err is None and req is not None and req.op == "stop" and self.stop is not None:
            log.info("%s %s: stopped for a handover", self.name, self.instance)
            self.stop.set()

    def _serve(self, req: HandoverRequest, prepare: Callable[[], None]) -> HandoverReply:
        if req.op == "pause" and not self.paused:
            prepare()
            self._checkpoint()
            self.paused = True
            log.info("%s %s: paused for a handover (log head %d)", self.name, self.instance,
                     self.head())  # fmt: skip
        elif req.op == "resume" and self.paused:
            self._resume("handover called off")
        elif req.op in ("state", "stop", "cut") and not self.paused:
            raise DecodeError("op", f"{req.op}: not paused (pause first)")
        elif req.op in ("state", "stop") and self.advancing:
            raise DecodeError("op", f"{req.op}: still applying up to the cut (ask status)")
        elif req.op == "cut":
            self._cut(dict(req.cut))
        size = self.path.stat().st_size if self.paused else 0
        data = b""
        if req.op == "state":
            if req.offset > size:
                raise DecodeError("offset", f"{req.offset} is past the checkpoint ({size} bytes)")
            with self.path.open("rb") as f:
                f.seek(req.offset)
                data = f.read(CHUNK_BYTES)
        return HandoverReply(
            self.name,
            self.instance,
            self.region_label,
            self.paused,
            self.head(),
            self.marks(),
            size,
            req.offset,
            data,
            tuple(sorted(self.inputs().items())),
            self.at_cut,
        )

    def _cut(self, cut: dict[str, int]) -> None:
        if cut == self.cut:
            return  # asked again
        for p, g in sorted(self.inputs().items()):
            if g > cut.get(p, 0):
                raise DecodeError(
                    "cut", f"{p}: applied up to gseq {g}, past the cut at {cut.get(p, 0)}"
                )
        self.cut, self.at_cut = cut, False
        self.hold(cut)
        log.info("%s %s: applying up to the cut %s", self.name, self.instance, cut)

    def lease_over(self) -> bool:
        """Paused, and no request for :data:`LEASE_S`: the tool is gone; the caller
        resumes (a warning, counted ``handover_expired``)."""
        if self.paused and self.clock() - self.asked_at > LEASE_S:
            self._resume(f"no handover request for {LEASE_S:g} s", logging.WARNING)
            return True
        return False

    def _resume(self, why: str, level: int = logging.INFO) -> None:
        self.paused = False
        if self.cut is not None:
            self.cut, self.at_cut = None, False
            self.hold(None)
        self.path.unlink(missing_ok=True)
        log.log(level, "%s %s: %s: applying again", self.name, self.instance, why)

    def marks(self) -> tuple[tuple[str, int, float], ...]:
        """Every consumer's last mark on this log: (consumer, gseq, seconds since)."""
        try:
            rows = self.db.execute("SELECT consumer, gseq, at FROM log_marks ORDER BY consumer")
        except sqlite3.OperationalError:  # no output log: no consumers
            return ()
        now = time.time()
        return tuple((str(c), int(g), max(0.0, now - float(at))) for c, g, at in rows)

    def _checkpoint(self) -> None:
        """Copy the database as it is now (between transactions) to :attr:`path`."""
        tmp = self.path.with_suffix(".tmp")
        tmp.unlink(missing_ok=True)
        dst = sqlite3.connect(tmp)
        try:
            self.db.backup(dst)
        finally:
            dst.close()
        tmp.replace(self.path)
