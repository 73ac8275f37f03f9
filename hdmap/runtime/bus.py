"""Zenoh wiring shared by every process: config building, sessions, data-path publishers.

Facts this module encodes (measured with eclipse-zenoh 1.10.2; docs/architecture.md,
"Zenoh facts this code relies on"):

- the default congestion control drops under load, so data-path publishers are
  declared with ``CongestionControl.BLOCK`` and ``Reliability.RELIABLE``;
- a process exiting with its session open hangs, so sessions are opened with
  ``with open_session(...)`` or closed in ``finally``;
- multicast scouting is off unless asked for (tests and CI talk over 127.0.0.1 only).

A config file (Zenoh JSON5) is loaded first, then the explicit overrides, like the
zenoh-python examples.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass(frozen=True)
class BusConfig:
    """How a process joins the bus."""

    mode: str = "client"
    """'client' (services, vehicles), 'peer' or 'router'."""
    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    """Zenoh JSON5 config loaded first (security, TLS, ACL...); the fields above override it."""
    multicast_scouting: bool = False
    extra: tuple[tuple[str, str], ...] = field(default_factory=tuple)
    """Further (path, JSON5 value) overrides, e.g. ('transport/unicast/max_links', '2')."""

    def with_connect(self, endpoints: Iterable[str]) -> BusConfig:
        eps = tuple(endpoints)
        return (
            self
            if not eps
            else BusConfig(
                self.mode, eps, self.listen, self.config_file, self.multicast_scouting, self.extra
            )
        )


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    conf = zenoh.Config.from_file(cfg.config_file) if cfg.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    if cfg.connect and cfg.mode != "router":
        conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    if cfg.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    for path, value in cfg.extra:
        conf.insert_json5(path, value)
    return conf


@contextmanager
def open_session(cfg: BusConfig) -> Iterator[zenoh.Session]:
    """``with open_session(cfg) as s:`` always closes the session."""
    session = zenoh.open(zenoh_config(cfg))
    try:
        yield session
    finally:
        session.close()


class Publishers:
    """Data-path puts with ``CongestionControl.BLOCK`` (reliable, the default), any key.

    No publisher is declared per key: declaring one costs time that grows with the
    publishers a session already holds (about 7 ms each at 20,000), under the GIL, and
    an upload spread over many tiles would declare one per tile and keep it. A
    ``session.put`` costs the same for a new key as for an old one (about 12 us here, one
    subscriber matching; ``benchmarks/bench_keys.py``), and this object keeps no state
    per key, so what it costs and holds does not grow with the keys ever written.
    """

    def __init__(self, session: zenoh.Session):
        self._session = session

    def put(self, key: str, payload: bytes) -> None:
        self._session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def close(self) -> None:
        """Nothing declared, nothing to undeclare (kept for the service's shutdown path)."""


def query(
    session: zenoh.Session,
    selector: str,
    payload: bytes | None = None,
    timeout: float = 5.0,
    target: zenoh.QueryTarget | None = None,
) -> list[tuple[str, bytes | None, bytes | None]]:
    """A get with every reply kept (no consolidation): [(key, ok payload, error payload)]."""
    replies = session.get(
        selector,
        payload=payload,
        timeout=timeout,
        consolidation=zenoh.ConsolidationMode.NONE,
        target=target if target is not None else zenoh.QueryTarget.ALL,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    out: list[tuple[str, bytes | None, bytes | None]] = []
    for reply in replies:
        if reply.ok is not None:
            out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes(), None))
        else:
            out.append(("", None, reply.err.payload.to_bytes()))
    return out
