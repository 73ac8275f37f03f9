"""Catch-ups off the worker thread.

A catch-up waits for the producers' answers (up to the query timeout when one is slow or
gone); on the worker thread that wait held up every live entry behind it. Here the worker
builds each round's query from the consumer's state, one background thread waits for the
answers, and the worker absorbs them at its next turn (:meth:`BackgroundCatchUp.poll`), so
the consumer's state is only ever touched by the worker.

Invariant: at most one round is in flight; a round asked before a rewind of the consumer
(a rollback: :attr:`LogConsumer.generation`) is dropped unabsorbed, and the rewind asks
for a new one. Pitfall: what a round delivers may already have arrived live meanwhile;
:meth:`LogConsumer.offer` drops those as duplicates, as it does for any replay.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Executor, Future, ThreadPoolExecutor

import zenoh

from hdmap.runtime.bus import query
from hdmap.runtime.stream import LogConsumer
from schemas import LogEntry

log = logging.getLogger(__name__)

MAX_ROUNDS_PER_POLL = 1000
"""Rounds one poll may absorb when they complete at once (an executor running inline)."""

Fetch = Callable[[list[str], bytes], list[bytes]]
"""One round: (selectors, request) -> the producers' replies."""


class BackgroundCatchUp:
    """The consumer's catch-ups, one round at a time on ``executor`` (default: one thread
    of its own); ``wake`` is called when a round's answers are in (a kick in the inbox)."""

    def __init__(
        self,
        consumer: LogConsumer,
        fetch_round: Fetch,
        wake: Callable[[], None],
        limit: int = 2000,
        executor: Executor | None = None,
    ):
        self.consumer = consumer
        self._fetch = fetch_round
        self._wake = wake
        self.limit = limit
        self._executor = executor or ThreadPoolExecutor(1, thread_name_prefix="catch-up")
        self._own_executor = executor is None
        self._inflight: tuple[Future[list[bytes]], int] | None = None
        self.failures = 0
        """Rounds whose query failed (the bus): the catch-up is asked for again."""

    @property
    def busy(self) -> bool:
        """A round is in flight."""
        return self._inflight is not None

    def poll(self, now: float) -> list[LogEntry]:
        """Worker thread: absorb the rounds that are done and start the next one that is
        due; the entries now deliverable, in order."""
        out: list[LogEntry] = []
        for _ in range(MAX_ROUNDS_PER_POLL):
            if self._inflight is not None:
                fut, generation = self._inflight
                if not fut.done():
                    return out
                self._inflight = None
                out += self._absorb(fut, generation, now)
            if not self.consumer.wants_catchup(now):
                return out
            if not self.consumer.more:
                self.consumer.begin_catchup()
            request = self.consumer.query(self.limit).to_bytes()
            fut = self._executor.submit(self._fetch, self.consumer.selector(), request)
            self._inflight = (fut, self.consumer.generation)
            fut.add_done_callback(lambda _f: self._wake())
        return out

    def _absorb(self, fut: Future[list[bytes]], generation: int, now: float) -> list[LogEntry]:
        try:
            replies = fut.result()
        except (zenoh.ZError, OSError) as exc:
            log.warning("catch-up failed: %s", exc)
            self.failures += 1
            self.consumer.end_round(True, now)  # not cut short: a gap retries later
            return []
        if generation != self.consumer.generation:  # asked before a rollback: stale
            return []
        delivered, complete = self.consumer.absorb(replies)
        self.consumer.end_round(complete, now)
        return delivered

    def close(self) -> None:
        """Stop the thread (a round in flight ends with its query's timeout)."""
        if self._own_executor:
            self._executor.shutdown(wait=True, cancel_futures=True)


class InlineExecutor(Executor):
    """Runs each round at once on the caller's thread (tests, in-process replays): a
    catch-up then completes within the :meth:`BackgroundCatchUp.poll` that starts it."""

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[override]
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - handed to the future's reader
            fut.set_exception(exc)
        return fut


def bus_fetch(session: zenoh.Session, timeout: float = 5.0) -> Fetch:
    """Rounds asked on the bus (:func:`fetch`)."""
    return lambda selectors, request: fetch(session, selectors, request, timeout)


def fetch(
    session: zenoh.Session, selectors: list[str], request: bytes, timeout: float
) -> list[bytes]:
    """One catch-up round: the producers' replies to ``request``, their refusals
    (:class:`~schemas.ErrorReply`) included."""
    out = []
    for sel in selectors:
        for _key, ok, err in query(session, sel, request, timeout=timeout):
            if ok is not None or err is not None:
                out.append(ok if ok is not None else err)
    return out


def catch_up(
    consumer: LogConsumer,
    session: zenoh.Session,
    timeout: float = 5.0,
    limit: int = 2000,
    max_rounds: int = 1000,
) -> list[LogEntry]:
    """On the caller's thread: fetch what the producers have that ``consumer`` has not;
    return it deliverable, in order (tools and tests; services use
    :class:`BackgroundCatchUp`). Bounded: at most ``max_rounds`` queries of ``limit``
    entries per producer."""
    consumer.begin_catchup()
    out: list[LogEntry] = []
    for _ in range(max_rounds):
        request = consumer.query(limit).to_bytes()
        delivered, complete = consumer.absorb(fetch(session, consumer.selector(), request, timeout))
        out += delivered
        consumer.end_round(complete, consumer.clock())
        if complete:
            break
    return out
