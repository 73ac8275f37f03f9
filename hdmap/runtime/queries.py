"""Queryables answered off the Zenoh callback threads, from a read-only SQLite connection.

Invariant: the Zenoh callback never blocks. A query is checked by ``admit`` (cheap, on
the callback thread: per-client limits) and queued; when the queue is full it is
answered at once with an ``ErrorReply`` of code ``busy`` (counted by the owner through
``on_refused``) instead of waiting, because a callback that blocks stalls every other
delivery of the session (subscribers, other queryables, liveliness).
"""

from __future__ import annotations

import logging
import queue
import sqlite3
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import zenoh

from hdmap.runtime.store import connect
from schemas import ErrorReply

log = logging.getLogger(__name__)

BUSY = ErrorReply("busy", "query", "too many queries waiting; try again later")


class QueryServer:
    """A queryable (on one key expression or several) answered on its own thread from its
    own read-only SQLite connection.

    Keeps reads (replays, snapshots) off both the Zenoh callback threads and the
    service's worker; WAL lets it read committed state while the worker writes. The
    queries of all its keys share the one queue of at most ``max_queued``.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str | Sequence[str],
        db_path: str | Path,
        answer: Callable[[sqlite3.Connection, zenoh.Query], None],
        name: str = "query",
        admit: Callable[[zenoh.Query], ErrorReply | None] | None = None,
        on_refused: Callable[[ErrorReply], None] | None = None,
        max_queued: int = 1024,
        busy: ErrorReply = BUSY,
    ):
        """``admit`` runs on the Zenoh callback thread and must be cheap: it returns the
        error to answer at once, or None to queue the query. ``on_refused`` is told of
        every query answered with an error without being served (refused by ``admit``
        or because ``max_queued`` queries are waiting: then the error is ``busy``); it
        runs on the callback thread too."""
        self._db_path = db_path
        self._answer = answer
        self._admit = admit
        self._on_refused = on_refused
        self._busy = busy
        self._queue: queue.Queue[zenoh.Query | None] = queue.Queue(maxsize=max_queued)
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
        self._thread.start()
        key_exprs = [key] if isinstance(key, str) else list(key)
        self._queryables = [session.declare_queryable(k, self._offer) for k in key_exprs]

    def _offer(self, q: zenoh.Query) -> None:
        """The Zenoh callback: refuse, or queue without blocking."""
        err = self._admit(q) if self._admit is not None else None
        if err is None:
            try:
                self._queue.put_nowait(q)
                return
            except queue.Full:
                err = self._busy
        try:
            q.reply_err(err.to_bytes())
        except zenoh.ZError as exc:  # the querier is gone: nothing to tell
            log.debug("error reply on %s failed: %s", q.key_expr, exc)
        finally:
            q.drop()
        if self._on_refused is not None:
            self._on_refused(err)

    def close(self) -> None:
        for qbl in self._queryables:
            qbl.undeclare()
        self._queue.put(None)  # blocks only until the thread has taken a waiting query
        self._thread.join(timeout=5)

    def _serve(self) -> None:
        conn = connect(self._db_path, readonly=True)
        try:
            while (q := self._queue.get()) is not None:
                try:
                    self._answer(conn, q)
                except Exception:  # one bad query must not stop the thread
                    log.exception("query on %s failed", q.key_expr)
                finally:
                    q.drop()
        finally:
            conn.close()
