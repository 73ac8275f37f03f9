"""Wait until a pipeline has applied everything it accepted (for demos, tests, evals).

The chain is quiet when every stage has applied every entry its upstream wrote
(ingest log entries = matcher applied, matcher log entries = solver applied,
solver log entries = publisher applied), nothing is queued or being applied (``backlog``
and ``applying`` 0 everywhere), and the publisher has no unpublished change. Bounded in
time. The counters compared are committed ones (a transaction's counts appear at its
commit), so a long apply that later rolls back shows as ``applying``, never as quiet.
"""

from __future__ import annotations

import time

import zenoh

from hdmap.ops.status import collect
from schemas import Stats

CHAIN = (("ingest", "matcher"), ("matcher", "solver"), ("solver", "publisher"))


def totals(stats: list[Stats]) -> dict[str, dict[str, float]]:
    """Counters summed per service over its instances."""
    out: dict[str, dict[str, float]] = {}
    for s in stats:
        agg = out.setdefault(s.service, {})
        for k, v in s.counters.items():
            agg[k] = agg.get(k, 0.0) + float(v)
    return out


def is_quiet(t: dict[str, dict[str, float]]) -> bool:
    """Whether summed counters ``t`` (:func:`totals`) show a quiet chain (module docstring)."""
    for up, down in CHAIN:
        if up not in t or down not in t:
            return False
        if t[up].get("log_entries", 0) != t[down].get("entries_applied", 0):
            return False
    if any(v.get("backlog", 0) or v.get("applying", 0) for v in t.values()):
        return False
    return t["publisher"].get("dirty", 0) == 0


def wait_quiet(session: zenoh.Session, timeout: float = 120.0, settle: float = 0.6) -> bool:
    """Until the chain is quiet twice, ``settle`` seconds apart (bounded); whether it was."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        t = totals(collect(session, timeout=2.0))
        if is_quiet(t):
            sig = tuple(t[s].get("entries_applied", 0) for s in ("matcher", "solver", "publisher"))
            if sig == last:
                return True
            last = sig
            time.sleep(settle)
        else:
            last = None
            time.sleep(0.1)
    return False
