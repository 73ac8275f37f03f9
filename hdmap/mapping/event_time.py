"""What the matcher's clock moving on settles: the timers that decide what the map contains.

The clock is event time (:meth:`hdmap.mapping.matching.Matching.entry_time`: the entries'
capture times, clamped by their ingest stamps, monotone). After each obs entry
:func:`advance` runs

- the probation time-outs and forgotten trust records (:func:`hdmap.mapping.probation.
  follow_time`; their work is the vehicles due, so they run at every entry), and
- when the clock has entered a new sweep period (``MatchingConfig.sweep_every_s``, a
  minute of event time): pending rays past ``pending_ttl_s`` expire (counted
  ``expired``), budget records of passes silent that long go, and passes quiet for
  ``close_passes_after_s`` close in the gating sums (counted ``passes_closed``).

Invariant: every one of these runs at a point of the entry sequence fixed by the entries
alone (the entry that moved the clock), never by a wall-clock timer or by where a batch
ends, so the same entries give the same map live, a day late in one bulk, in a catch-up
and on a replay. Pitfall: a wall-clock timer that expires rays (as the matcher had)
makes the map depend on how fast the entries came: uploads sent in bulk never expired and
rays of passes hundreds apart started landmarks together (ghosts, issue 18).

After a restart the sweep period is that of the restored clock (the entry that moved it
there has swept); open passes are quiet from the restored clock on
(:func:`hdmap.mapping.quiet.note_open`: their last ray's time is not stored, so a pass
open at a restart closes up to ``close_passes_after_s`` later than it would have).
"""

from __future__ import annotations

from hdmap.mapping.matching import Matching
from hdmap.mapping.pending import expire, forget_budgets
from hdmap.mapping.probation import follow_time
from hdmap.mapping.quiet import close_quiet


def sweep(m: Matching) -> None:
    """Expire pending rays, forget silent budget records and close quiet passes, at the
    matcher's clock (counted ``expired``, ``passes_closed``)."""
    n = expire(m)
    if n:
        m.tally("expired", n)
    forget_budgets(m)
    closed = close_quiet(m.quiet, m.sums, m.state)
    if closed:
        m.tally("passes_closed", closed)


def advance(m: Matching) -> bool:
    """After an obs entry: settle what the clock's advance settles (see the module);
    returns whether it swept."""
    follow_time(m)
    if not m.sweeps.due(m.now):
        return False
    sweep(m)
    return True
