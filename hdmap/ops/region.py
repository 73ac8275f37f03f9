"""Rescaling a live region: ``hdmap region split`` and ``merge`` (issue 20).

A split hands a running region's matcher and solver state to sub-region instances:

1. pause the region's matcher (:mod:`hdmap.runtime.handover`): it applies nothing more,
   its last state is checkpointed; ingest keeps logging observations; regions to be
   merged are then brought to one position of ingest's log (:func:`cut_at_one_position`);
2. wait until every consumer of the matcher's log (the solver) has applied it to its
   head (their marks, which they send every ``catchup_interval_s``);
3. pause the solver the same way and wait until its consumers (publishers) have its log;
4. read both checkpoints over the bus and cut each into the sub-regions' data dirs
   (:mod:`hdmap.runtime.partition`, the rules in ``services/*/partition.py``);
5. stop the paused instances.

Then the operator starts a matcher and a solver per sub-region on those data dirs (the
tool prints the commands): each goes on from its region's offsets in ingest's log, as a
new producer whose log its consumers read from the start. Nothing acknowledged is lost
(ingest's log keeps what came during the pause) and nothing is applied twice (the
offsets were checkpointed with the state). The pause lasts from step 1 until the new
instances run: observations are acknowledged all along and mapped after it. A merge is
the same with several regions paused and one joined data dir.

Pitfall: every consumer must be running while the tool waits (step 2 and 3): one down
then misses the paused instance's last entries, which no one serves once it stopped.
"""

from __future__ import annotations

import logging
import shutil
import sqlite3
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from hdmap.geo.tiles import region_label
from hdmap.runtime.bus import query
from hdmap.runtime.partition import Rules, merge, split
from schemas import DecodeError, ErrorReply, HandoverReply, HandoverRequest, keys
from services.matcher.partition import RULES as MATCHER_RULES
from services.solver.partition import RULES as SOLVER_RULES

log = logging.getLogger(__name__)

SERVICES: tuple[tuple[str, Rules], ...] = (("matcher", MATCHER_RULES), ("solver", SOLVER_RULES))
"""The stateful services of a region, upstream first."""


class HandoverError(RuntimeError):
    """A handover step failed (nothing answered, a refusal, a consumer that never drained)."""


@dataclass
class Timing:
    """Bounds of the waits (seconds)."""

    reply_s: float = 10.0
    drain_s: float = 120.0
    """Longest wait for the consumers to apply a paused instance's log."""
    settle_s: float = 12.0
    """Marks are fresh when younger than this (consumers send one every
    ``catchup_interval_s``, 5 s by default); the tool waits at least this long for them."""


@dataclass
class Report:
    """What a split or merge did (for the command's output and tests)."""

    data_dirs: list[Path] = field(default_factory=list)
    pause_s: float = 0.0


def parse_region(text: str) -> list[str]:
    """'120+121' (or 'all') as its prefixes."""
    return [] if text == "all" else sorted(text.split("+"))


def covers(whole: Sequence[str], parts: Sequence[Sequence[str]]) -> str | None:
    """None if the parts' prefixes lie inside ``whole``, do not overlap and cover it; else
    what is wrong.

    >>> covers(["12"], [["120", "121"], ["122", "123"]]) is None
    True
    >>> covers(["12"], [["120"], ["121"]])
    'tile 122 of region 12 is in no part'
    """
    flat = [p for part in parts for p in part]
    for a in flat:
        if whole and not any(a.startswith(w) for w in whole):
            return f"{a} is not inside region {region_label(whole)}"
        for b in flat:
            if a is not b and b.startswith(a):
                return f"parts overlap: {a} and {b}"
    depth = max(len(p) for p in flat)
    for w in whole or [""]:
        if depth - len(w) > 8:
            return f"parts more than 8 levels below {w or 'all'}"
        todo = [w]
        while todo:
            t = todo.pop()
            if any(t.startswith(p) for p in flat):
                continue
            if len(t) >= depth:
                return f"tile {t} of region {region_label(whole)} is in no part"
            todo.extend(t + d for d in "3210")
    return None


def ask(session: zenoh.Session, service: str, region: str, op: str, offset: int = 0,
        timeout: float = 10.0, cut: tuple[tuple[str, int], ...] = ()) -> HandoverReply:  # fmt: skip
    """One handover request to the region's instance; exactly one must answer."""
    got = query(session, keys.handover(service, region),
                HandoverRequest(op, offset, cut).to_bytes(), timeout)  # fmt: skip
    if not got:
        raise HandoverError(f"no {service} of region {region} answered (is it running?)")
    if len(got) > 1:
        raise HandoverError(f"{len(got)} {service} instances of region {region} answered")
    _key, ok, err = got[0]
    if ok is None:
        e = ErrorReply.from_bytes(err or b"")
        raise HandoverError(f"{service} {region} refused {op}: {e.field}: {e.reason}")
    try:
        return HandoverReply.from_bytes(ok)
    except DecodeError as exc:
        raise HandoverError(f"{service} {region}: bad handover reply: {exc}") from exc


def wait_drained(session: zenoh.Session, service: str, region: str, timing: Timing,
                 need_consumer: bool) -> HandoverReply:  # fmt: skip
    """Until every consumer with a fresh mark has applied the paused instance's log to its
    head (at least ``settle_s``: a consumer's next mark comes within it)."""
    start = time.monotonic()
    deadline = start + timing.drain_s
    while True:
        r = ask(session, service, region, "status", timeout=timing.reply_s)
        fresh = [(c, g) for c, g, age in r.marks if age <= timing.settle_s]
        behind = [c for c, g in fresh if g < r.head]
        settled = time.monotonic() - start >= timing.settle_s
        if settled and not behind and (fresh or not need_consumer):
            return r
        if time.monotonic() > deadline:
            raise HandoverError(
                f"{service} {region}: consumers did not apply its log to {r.head} in "
                f"{timing.drain_s:g} s (behind: {behind or 'none with a fresh mark'})"
            )
        time.sleep(0.5)


def cut_at_one_position(
    session: zenoh.Session,
    paused: Sequence[HandoverReply],
    timing: Timing,
    progress: Callable[[str], None],
) -> dict[str, int]:
    """Bring paused instances of regions to be joined to one position of their input: per
    producer the furthest any of them applied; each applies its region's entries up to it
    and holds (``cut``). Returned: the cut.

    Why: a joined instance goes on from the latest of its parts' clocks (the matcher's
    event time). A part stopped behind the others would apply its catch-up against that
    later clock, where the unsplit region had applied it at its own time (the matcher's
    gating ticks: :attr:`hdmap.mapping.matching.MatchingConfig.tick_lag_s`)."""
    cut: dict[str, int] = {}
    for r in paused:
        for p, g in r.inputs:
            cut[p] = max(cut.get(p, 0), g)
    items = tuple(sorted(cut.items()))
    for r in paused:
        ask(session, r.service, r.region, "cut", timeout=timing.reply_s, cut=items)
    deadline = time.monotonic() + timing.drain_s
    todo = list(paused)
    while todo:
        r = todo[0]
        now = ask(session, r.service, r.region, "status", timeout=timing.reply_s)
        if now.at_cut:
            progress(f"{r.service} {r.region}: holds at the cut {dict(now.inputs)}")
            todo.pop(0)
            continue
        if time.monotonic() > deadline:
            raise HandoverError(
                f"{r.service} {r.region}: did not reach the cut {cut} in {timing.drain_s:g} s "
                f"(applied {dict(now.inputs)})"
            )
        time.sleep(0.2)
    return cut


def fetch_state(session: zenoh.Session, service: str, region: str, out: Path,
                timing: Timing) -> None:  # fmt: skip
    """The paused instance's checkpoint, in chunks, to ``out``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".part")
    offset, size = 0, None
    with tmp.open("wb") as f:
        while size is None or offset < size:
            r = ask(session, service, region, "state", offset, timing.reply_s)
            size = r.size
            if not r.data and offset < size:
                raise HandoverError(f"{service} {region}: empty chunk at {offset} of {size}")
            f.write(r.data)
            offset += len(r.data)
    tmp.replace(out)


def handover(
    session: zenoh.Session,
    old: Sequence[Sequence[str]],
    new: Sequence[Sequence[str]],
    data_dir: Path,
    timing: Timing | None = None,
    progress: Callable[[str], None] = lambda s: None,
) -> Report:
    """Pause the regions ``old`` (their matcher, then their solver), cut or join their
    checkpoints into the data dirs of the regions ``new`` and stop them (the module
    docstring). One old region and several new: a split; several old and one new: a merge."""
    timing = timing or Timing()
    if len(old) != 1 and len(new) != 1:
        raise HandoverError("either one region split into several or several merged into one")
    whole = [p for r in old for p in r]
    why = covers(whole, new) if len(old) == 1 else covers(new[0], old)
    if why:
        raise HandoverError(why)
    labels = [region_label(r) for r in old]
    targets = [data_dir / f"{svc}-{region_label(r)}" for svc, _ in SERVICES for r in new]
    there = [str(t) for t in targets if (t / "state.sqlite").exists()]
    if there:
        raise HandoverError(f"data dirs exist already: {', '.join(there)}")
    report = Report()
    t0 = time.monotonic()
    for svc, rules in SERVICES:
        paused = []
        for label in labels:
            r = ask(session, svc, label, "pause", timeout=timing.reply_s)
            progress(f"{svc} {label} ({r.instance}) paused at log head {r.head}")
            paused.append(r)
        if len(paused) > 1:
            cut_at_one_position(session, paused, timing, progress)
        for label in labels:
            wait_drained(session, svc, label, timing, need_consumer=svc == "matcher")
            progress(f"{svc} {label}: its consumers have applied its log")
        parts = []
        for label in labels:
            cp = data_dir / ".handover" / f"{svc}-{label}.sqlite"
            cp.unlink(missing_ok=True)
            fetch_state(session, svc, label, cp, timing)
            parts.append(cp)
            progress(f"{svc} {label}: checkpoint {cp.stat().st_size / 1e6:.1f} MB")
        for i, r in enumerate(new):
            out = data_dir / f"{svc}-{region_label(r)}" / "state.sqlite"
            try:
                if len(parts) == 1:
                    split(parts[0], out, r, rules, first=i == 0)
                else:
                    merge(parts, out, rules)
            except (sqlite3.Error, ValueError, OSError) as exc:
                for d in [*report.data_dirs, out.parent]:  # none of it is usable alone
                    shutil.rmtree(d, ignore_errors=True)
                raise HandoverError(f"{svc}: cannot cut its checkpoint: {exc}") from exc
            report.data_dirs.append(out.parent)
            progress(f"{svc} {region_label(r)}: data dir {out.parent}")
        for cp in parts:  # cut: the copies are spent
            cp.unlink()
    for svc, _ in SERVICES:
        for label in labels:
            r = ask(session, svc, label, "stop", timeout=timing.reply_s)
            wait_gone(session, svc, label, r.instance, timing.reply_s)
            progress(f"{svc} {label} stopped")
            retire_data_dir(data_dir / f"{svc}-{label}", progress)
    report.pause_s = time.monotonic() - t0
    return report


def wait_gone(session: zenoh.Session, service: str, region: str, instance: str,
              timeout: float) -> None:  # fmt: skip
    """Until the instance's liveliness token is gone (its process has closed its database)."""
    key = keys.alive(service, region, instance)
    deadline = time.monotonic() + timeout
    while any(r.ok is not None for r in session.liveliness().get(key, timeout=1.0)):
        if time.monotonic() > deadline:
            raise HandoverError(f"{service} {region} ({instance}) did not stop in {timeout:g} s")
        time.sleep(0.2)


def retire_data_dir(path: Path, progress: Callable[[str], None]) -> None:
    """Move a handed-over region's data dir out of the way (it is stale: an instance run on
    it again would map its region a second time), kept as ``NAME.handed-over-TIME``."""
    if not path.exists():
        return  # on another host: the operator retires it there
    stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
    to = path.with_name(f"{path.name}.handed-over-{stamp}")
    path.rename(to)
    progress(f"old data dir kept as {to}")


def resume(session: zenoh.Session, regions: Sequence[Sequence[str]], timing: Timing) -> None:
    """Call a handover off: the paused instances apply their input again."""
    for svc, _ in SERVICES:
        for r in regions:
            ask(session, svc, region_label(r), "resume", timeout=timing.reply_s)
