"""Status client: the live services of a deployment and their stats (by liveliness).

A liveliness token is only a claim: in the default (unsecured) mode anyone may declare
one. So a token whose key is not one concrete ``alive/<service>/<region>/<instance>``
(a wildcard such as ``alive/ingest/*/*``, or the wrong depth) is ignored, a service is
counted only from the stats its own queryable answers, and each (service, instance) once.
"""

from __future__ import annotations

from hdmap.runtime.bus import query
from schemas import DecodeError, Stats, keys

_ALIVE = f"{keys.ROOT}/alive/"


def concrete_instance(key: str) -> tuple[str, str, str] | None:
    """(service, region, instance) of a liveliness key, or None if it is not one concrete
    instance's key.

    >>> concrete_instance("hdmap/v1/alive/ingest/all/abc")
    ('ingest', 'all', 'abc')
    >>> concrete_instance("hdmap/v1/alive/ingest/*/*") is None
    True
    """
    if not key.startswith(_ALIVE) or "*" in key or "$" in key:
        return None
    parts = key[len(_ALIVE) :].split("/")
    if len(parts) != 3 or not all(parts):
        return None
    return parts[0], parts[1], parts[2]


def collect(session, timeout: float = 3.0) -> list[Stats]:
    """Stats of every live service instance (by liveliness, then their stats queryables)."""
    alive = {
        inst
        for r in session.liveliness().get(f"{keys.ROOT}/alive/**", timeout=timeout)
        if r.ok and (inst := concrete_instance(str(r.ok.key_expr))) is not None
    }
    out: dict[tuple[str, str], Stats] = {}
    for service, region, instance in sorted(alive):
        for _k, ok, _err in query(session, keys.stats(service, region, instance), timeout=timeout):
            if ok is None:
                continue
            try:
                s = Stats.from_bytes(ok)
            except DecodeError:
                continue
            if (s.service, s.instance) == (service, instance):
                out.setdefault((service, instance), s)
    return [out[k] for k in sorted(out)]
