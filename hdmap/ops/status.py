"""Status client: the live services of a deployment and their stats (by liveliness)."""

from __future__ import annotations

from hdmap.runtime.bus import query
from schemas import DecodeError, Stats, keys


def collect(session, timeout: float = 3.0) -> list[Stats]:
    """Stats of every live service instance (by liveliness, then their stats queryables)."""
    alive = [
        str(r.ok.key_expr)
        for r in session.liveliness().get(f"{keys.ROOT}/alive/**", timeout=timeout)
        if r.ok
    ]
    out: list[Stats] = []
    for key in sorted(alive):
        service, region, instance = key.split("/")[-3:]
        for _k, ok, _err in query(session, keys.stats(service, region, instance), timeout=timeout):
            if ok is not None:
                try:
                    out.append(Stats.from_bytes(ok))
                except DecodeError:
                    pass
    return out
