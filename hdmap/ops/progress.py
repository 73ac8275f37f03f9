"""A progress line for long work (evaluations, load tests, soaks, exports): no dependency.

:class:`Progress` writes to stderr. On a terminal it redraws one line in place (``\\r``),
at most every ``redraw_s``; elsewhere (CI logs, a file) it prints a plain line each time
the work crosses another ``every_pct`` per cent, so a log gets about ten lines however long
the run. The line shows done/total, the rate and the ETA (from the mean rate since the
start); with no total, done and the rate only (and on a log, a line every ``every_s``).
:meth:`Progress.note` prints a message on a line of its own without garbling the bar.
Work done in worker processes reports through a :class:`Relay` (:func:`relayed`,
:func:`wait_relayed`): the workers' ticks and messages reach the parent's bar.

It is off with ``enabled=False`` (a command's ``--no-progress``) or when the environment
has ``HDMAP_NO_PROGRESS=1``: then :meth:`Progress.update` draws nothing and
:meth:`Progress.note` still prints its message (those are the run's log lines).

>>> import io
>>> t = [0.0]
>>> out = io.StringIO()
>>> p = Progress(4, "passes", stream=out, tty=False, every_pct=50, clock=lambda: t[0])
>>> for _ in range(4):
...     t[0] += 2.0
...     p.update()
>>> p.close()
>>> print(out.getvalue(), end="")
passes: 2/4 (50 %), 0.50/s, ETA 4s
passes: 4/4 (100 %), 0.50/s, 8s
"""

from __future__ import annotations

import concurrent.futures
import math
import multiprocessing
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any, TextIO

ENV_OFF = "HDMAP_NO_PROGRESS"
"""An environment variable that turns every progress line off (``1``, ``true``, ``yes``)."""

BAR_WIDTH = 20


def progress_wanted(no_progress: bool = False) -> bool:
    """Whether progress lines are wanted: not ``--no-progress``, not ``HDMAP_NO_PROGRESS``.

    >>> progress_wanted(True)
    False
    """
    if no_progress:
        return False
    return os.environ.get(ENV_OFF, "").strip().lower() not in ("1", "true", "yes", "on")


def format_duration(seconds: float) -> str:
    """A duration as ``42s``, ``3m05s`` or ``2h07m``; ``?`` when unknown.

    >>> format_duration(42.4), format_duration(185), format_duration(7625), format_duration(-1)
    ('42s', '3m05s', '2h07m', '?')
    """
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = round(seconds)
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{(s % 3600) // 60:02d}m"


def _number(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else f"{v:.1f}"


class Progress:
    """Progress of ``total`` units of work (None: unknown) on ``stream`` (stderr).

    ``tty`` (default: whether the stream is a terminal) chooses the redrawn bar or the
    plain lines; ``rate=False`` leaves the rate out (where done counts seconds, the rate
    says nothing); nothing is drawn before ``quiet_s`` have passed (work that ends sooner
    shows no progress at all). ``clock`` is injectable for tests. Thread-safe.
    """

    def __init__(
        self,
        total: float | None,
        label: str = "",
        *,
        unit: str = "",
        stream: TextIO | None = None,
        enabled: bool | None = None,
        tty: bool | None = None,
        every_pct: float = 10.0,
        every_s: float = 30.0,
        redraw_s: float = 0.2,
        rate: bool = True,
        quiet_s: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.total = None if total is None else max(float(total), 0.0)
        self.label = label
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = progress_wanted() if enabled is None else bool(enabled)
        self.tty = _isatty(self.stream) if tty is None else bool(tty)
        self.every_pct = max(float(every_pct), 0.1)
        self.every_s = every_s
        self.redraw_s = redraw_s
        self.show_rate = rate
        self.quiet_s = quiet_s
        self.clock = clock
        self.done = 0.0
        self.info = ""
        self.started = clock()
        self._lock = threading.Lock()
        self._next_pct = self.every_pct
        """The per cent at which the next plain line is due."""
        self._last_line = self.started
        self._last_draw = -math.inf
        self._drawn = 0
        """Characters of the bar now on the terminal's line (0: none)."""
        self._shown = False
        """Whether anything was drawn or printed yet."""
        self._closed = False

    # -- what the caller calls --------------------------------------------------------------

    def update(self, n: float = 1.0, info: str | None = None) -> None:
        """``n`` more units done; ``info`` replaces the text shown after the counts."""
        self.set(self.done + n, info)

    def set(self, done: float, info: str | None = None) -> None:
        """``done`` units done in all."""
        with self._lock:
            self.done = float(done)
            if info is not None:
                self.info = info
            if not self.enabled or self._closed:
                return
            now = self.clock()
            if now - self.started < self.quiet_s:
                return
            if self.tty:
                if now - self._last_draw >= self.redraw_s or self._complete():
                    self._draw(now)
            elif self._line_due(now):
                self._emit(self.line(now))
                self._last_line = now

    def note(self, message: str) -> None:
        """``message`` on a line of its own (also when progress is off); the bar is drawn
        again under it."""
        with self._lock:
            self._clear()
            self.stream.write(message + "\n")
            self.stream.flush()
            if self.enabled and self.tty and not self._closed and self._last_draw > -math.inf:
                self._draw(self.clock())

    def close(self) -> None:
        """The last line: on a terminal the bar as it ends, then a newline; on a log a final
        line unless the last one already said 100 %."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if not self.enabled:
                return
            now = self.clock()
            if not self._shown and now - self.started < self.quiet_s:
                return  # over before it was worth showing
            if self.tty:
                if self._last_draw > -math.inf:
                    self._draw(now)
                    self.stream.write("\n")
                    self.stream.flush()
                    self._drawn = 0
            elif self._next_pct <= 100.0 or self.total is None:
                self._emit(self.line(now))

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the text -----------------------------------------------------------------------------

    def eta_s(self, now: float | None = None) -> float | None:
        """Seconds left at the mean rate so far; None with no total or nothing done yet."""
        now = self.clock() if now is None else now
        if self.total is None or self.done <= 0:
            return None
        left = max(self.total - self.done, 0.0)
        return (now - self.started) * left / self.done

    def line(self, now: float | None = None, bar: bool = False) -> str:
        """The progress text: ``label: done/total (pct %), rate/s, ETA t`` (with ``bar``, a
        bar of ``BAR_WIDTH`` cells after the label)."""
        now = self.clock() if now is None else now
        elapsed = max(now - self.started, 0.0)
        unit = f" {self.unit}" if self.unit else ""
        parts = []
        if self.total is None:
            parts.append(f"{_number(self.done)}{unit}")
        else:
            pct = 100.0 * self.done / self.total if self.total > 0 else 100.0
            cells = min(BAR_WIDTH, int(BAR_WIDTH * pct / 100.0))
            head = f"[{'#' * cells}{'.' * (BAR_WIDTH - cells)}] " if bar else ""
            parts.append(f"{head}{_number(self.done)}/{_number(self.total)}{unit} ({pct:.0f} %)")
        if self.show_rate and elapsed > 0:
            parts.append(f"{self.done / elapsed:.2f}/s")
        if self.total is not None and self.done >= self.total:
            parts.append(format_duration(elapsed))
        elif (eta := self.eta_s(now)) is not None:
            parts.append(f"ETA {format_duration(eta)}")
        if self.info:
            parts.append(self.info)
        text = ", ".join(parts)
        return f"{self.label}: {text}" if self.label else text

    # -- drawing ------------------------------------------------------------------------------

    def _complete(self) -> bool:
        return self.total is not None and self.done >= self.total

    def _line_due(self, now: float) -> bool:
        """On a log: whether the work crossed the next ``every_pct`` (then the mark moves
        past what is done, so one line however many marks were crossed), or with no total
        whether ``every_s`` passed."""
        if self.total is None:
            return now - self._last_line >= self.every_s
        pct = 100.0 * self.done / self.total if self.total > 0 else 100.0
        if pct + 1e-9 < self._next_pct:
            return False
        self._next_pct = (math.floor(pct / self.every_pct + 1e-9) + 1) * self.every_pct
        return True

    def _draw(self, now: float) -> None:
        text = self.line(now, bar=True)
        pad = max(self._drawn - len(text), 0)
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._drawn = len(text)
        self._last_draw = now
        self._shown = True

    def _clear(self) -> None:
        if self._drawn:
            self.stream.write("\r" + " " * self._drawn + "\r")
            self._drawn = 0

    def _emit(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()
        self._shown = True


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class Relay:
    """What worker processes report to the parent's :class:`Progress`: picklable (it goes to
    the workers with their task); :meth:`tick` counts work done, :meth:`say` a message. With
    no queue (progress off) ticks are dropped and messages printed on the worker's stderr."""

    def __init__(self, q: Any = None):
        self.queue = q

    def tick(self, n: float = 1.0) -> None:
        if self.queue is not None:
            self.queue.put(("tick", n))

    def say(self, message: str) -> None:
        if self.queue is None:
            print(message, file=sys.stderr, flush=True)
        else:
            self.queue.put(("say", message))


@contextmanager
def relayed(bar: Progress) -> Iterator[Relay]:
    """A :class:`Relay` into ``bar`` (through a ``multiprocessing.Manager`` queue, so any
    worker process can use it), emptied into the bar on leaving; with the bar off, a relay
    without a queue (no manager process)."""
    if not bar.enabled:
        yield Relay()
        return
    with multiprocessing.Manager() as manager:
        relay = Relay(manager.Queue())
        try:
            yield relay
        finally:
            pump(relay, bar)


def pump(relay: Relay, bar: Progress) -> None:
    """Everything the workers reported so far into ``bar`` (does not block)."""
    if relay.queue is None:
        return
    ticks = 0.0
    while True:
        try:
            kind, value = relay.queue.get_nowait()
        except queue.Empty:
            break
        if kind == "tick":
            ticks += value
        else:
            bar.note(str(value))
    if ticks:
        bar.update(ticks)


def wait_relayed(
    futures: Iterable[concurrent.futures.Future], relay: Relay, bar: Progress, poll_s: float = 0.2
) -> None:
    """Until every future is done (each ends: it returns or raises), moving the workers'
    reports into ``bar`` every ``poll_s``."""
    pending = set(futures)
    while pending:
        _done, pending = concurrent.futures.wait(pending, timeout=poll_s)
        pump(relay, bar)
