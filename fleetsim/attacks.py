"""Attacks from one vehicle or one client (issue #17, "One vehicle must not stop a region").

Each attack is a thread (:class:`Attack`) with a bus session of its own (one client),
sending at a paced rate until its ``duration_s`` has passed or :meth:`Attack.stop`
is called (every request is bounded by its timeout); :meth:`Attack.report` is what it
sent and what came back (:class:`AttackReport`). The attacks (:data:`ATTACK_NAMES`,
:func:`make_attack`):

- ``restart``: :class:`StuckPass` with image indices that restart in every upload (three
  rays, images 0, 1, 2, of one phantom sign, in one pass): the rays meet, but never in the
  four distinct images a candidate landmark needs;
- ``parked``: :class:`StuckPass` of a parked car seeing the same sign from the same spot
  with no usable range (ten rays an upload, images counting up, ``range_m = 0``);
- ``spread``: :class:`SpreadUpload`, uploads of 10,000 observations spread over the globe
  (one obs log entry per tile: 10,000 tiles an upload);
- ``tokens``: :class:`ForgedTokens`, liveliness tokens with wildcards
  (``hdmap/v1/alive/ingest/*/*``, ...) declared and undeclared again and again;
- ``snapshots``: :class:`SnapshotQueries` from one client id on its own snapshot key
  (``hdmap/v1/map/<tile>/by/<id>``), hundreds a second: the publisher's per-client limit
  refuses it (``rate``, ``snapshot.client``) past its burst;
- ``sybil``: :class:`SnapshotQueries` under a new made-up client id every query (what an
  unauthenticated client can do): each id is within its own budget, only the publisher's
  total budget holds it (``busy``, ``snapshot.total``);
- ``wildcard``: :class:`SnapshotQueries` on ``hdmap/v1/**`` (every queryable of the
  deployment matches: snapshots, uploads, log replays, stats);
- ``newcomers``: :class:`Newcomers`, a new made-up vehicle id every upload (125 a second);
- ``future``: :class:`FutureDated`, uploads sent in 2096 (``sent_at``) whose rows are
  captured either just inside ingest's clock-skew window (``max_future_s``) or a year
  ahead.

The builders (:func:`fresh_observations`, :func:`stuck_pass_rays`, :func:`spread_rays`)
are shared with the fuzz tests (``tests/support/hostile.py``); running attacks under an
honest load is :mod:`fleetsim.attack_run`.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import zenoh

from fleetsim.synthetic import make_observations, ray_observations
from fleetsim.world import HELSINKI as HELSINKI_TOWN
from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.tiles import quadkeys_of
from hdmap.runtime.bus import BusConfig, open_session, query
from schemas import DecodeError, ErrorReply, ObservationBatch, Observations, UploadAck, keys

HELSINKI = (60.17, 24.94)
"""Where the fuzz tests' observations are (lat, lon deg)."""

TOWN = HELSINKI_TOWN[:2]
"""The demo town's anchor (lat, lon deg): where the load generator drives."""

PHANTOM_CLASS = 6
"""Sign class of the stuck passes' phantom sign: none of the demo town's signs has it, so
no honest landmark takes the rays."""

PHANTOM_SIGN = np.array([10.0, 30.0, 2.5])
"""The phantom sign in the town's ENU frame (m)."""

ATTACK_NAMES = (
    "restart",
    "parked",
    "spread",
    "tokens",
    "snapshots",
    "sybil",
    "wildcard",
    "future",
    "newcomers",
)
"""Every attack :func:`make_attack` builds, in the order of the issue."""

ATTACK_IDENTITIES = (
    ("restart", "attack-restart"),
    ("parked", "attack-parked"),
    ("spread", "attack-spread"),
    ("tokens", "forged-tokens"),
    ("snapshots", "snapshot-client"),
    ("sybil", "sybil"),
    ("wildcard", "wildcard-client"),
    ("future", "attack-future"),
    ("newcomers", "newcomer-0"),
)
"""The vehicle identity each attack authenticates as in secured mode (the id it sends
under; ``sybil`` and ``newcomers`` then claim other ids, which the router's ACL denies)."""


def attack_identity(name: str) -> str:
    """The vehicle identity of attack ``name`` in secured mode (:data:`ATTACK_IDENTITIES`)."""
    for attack, identity in ATTACK_IDENTITIES:
        if attack == name:
            return identity
    raise ValueError(f"unknown attack {name!r}; one of {', '.join(ATTACK_NAMES)}")


Pattern = Literal["restart", "parked"]
"""The two stuck passes (:func:`stuck_pass_rays`)."""

FORGED_TOKENS = (
    f"{keys.ROOT}/alive/ingest/*/*",
    f"{keys.ROOT}/alive/**",
    f"{keys.ROOT}/alive/matcher/*/*",
    f"{keys.ROOT}/alive/ingest/all/forged",
)
"""Liveliness keys :class:`ForgedTokens` declares (wildcards, and one with no service)."""

# --- builders -------------------------------------------------------------------------------


def fresh_observations(
    n: int, first_id: int, seed: int = 0, lat: float = HELSINKI[0], lon: float = HELSINKI[1]
) -> Observations:
    """Valid observations (:func:`fleetsim.synthetic.make_observations`) with the ids
    ``first_id .. first_id + n - 1``."""
    obs = make_observations(n, seed=seed, lat=lat, lon=lon)
    return replace(obs, obs_id=np.arange(first_id, first_id + n, dtype=np.uint64))


def stuck_pass_rays(
    frame: EnuFrame,
    pattern: Pattern,
    k: int,
    first_id: int,
    rng: np.random.Generator,
) -> Observations:
    """Upload ``k`` of a pass that never makes a landmark, ids from ``first_id``.

    ``restart``: three rays along 22 m of road at the phantom sign, images 0, 1, 2 in every
    upload (the GNSS bias drifts between uploads, as on a moving car); ``parked``: ten rays
    from one spot (GNSS jitter of a standing car), images counting up, no range."""
    n = 3 if pattern == "restart" else 10
    if pattern == "restart":
        a = np.c_[np.full(n, 12.0), np.linspace(0.0, 22.0, n), np.full(n, 1.5)]
        image = np.arange(n)
        a_meas = a + np.r_[rng.normal(0, 0.3, 2), 0.0]
    else:
        a = np.array([12.0, 0.0, 1.5]) + rng.normal(0, 0.01, (n, 3))
        image = np.arange(n) + k * n
        a_meas = a
    v = PHANTOM_SIGN - a
    v = v + rng.normal(0, 0.005, (n, 3)) * np.linalg.norm(v, axis=1)[:, None]
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    lat, lon, h = frame.to_geodetic(a_meas)
    ids = np.arange(first_id, first_id + n)
    return ray_observations(lat, lon, h, d, image, ids, PHANTOM_CLASS, t=time.time() - 0.5)


def spread_rays(n: int, first_id: int, rng: np.random.Generator) -> Observations:
    """``n`` valid observations spread over the globe (latitudes within +-80 deg), one
    image each, ids from ``first_id``."""
    obs = make_observations(n, seed=int(rng.integers(2**31)))
    return replace(
        obs,
        obs_id=np.arange(first_id, first_id + n, dtype=np.uint64),
        lat=rng.uniform(-80.0, 80.0, n),
        lon=rng.uniform(-180.0, 180.0, n),
        image=np.arange(n, dtype=np.uint32),
    )


# --- the attacks ----------------------------------------------------------------------------


@dataclass
class AttackReport:
    """What one attack sent and what came back: ``requests`` (uploads, queries or token
    declarations), ``observations`` (rows uploaded), ``accepted`` (rows acknowledged as
    recorded, ``UploadAck.accepted``), ``duplicates``, ``rejected`` (rows refused one by
    one), ``refused`` (requests refused whole: an ack with an error, an error reply),
    ``unanswered`` (no usable reply within the timeout), ``replies``, and ``errors``: the
    refusals and rejections by the field they name (``rate``, ``tile``, ``obs.t``, ...)."""

    name: str
    client: str
    """The vehicle id (uploads) or a label of the client."""
    seconds: float = 0.0
    requests: int = 0
    observations: int = 0
    accepted: int = 0
    duplicates: int = 0
    rejected: int = 0
    refused: int = 0
    unanswered: int = 0
    replies: int = 0
    errors: Counter[str] = field(default_factory=Counter)

    def as_dict(self) -> dict:
        """The report as plain JSON values."""
        return {**self.__dict__, "errors": dict(sorted(self.errors.items()))}


class Attack(threading.Thread):
    """One client's attack: :meth:`step` every ``period_s`` (paced; a late step runs at
    once) on a session of its own, until ``duration_s`` has passed or :meth:`stop`."""

    name_ = "attack"

    def __init__(self, bus: BusConfig, duration_s: float, period_s: float, client: str):
        super().__init__(name=f"attack-{self.name_}", daemon=True)
        self.bus, self.duration_s, self.period_s = bus, duration_s, period_s
        self._stop_event = threading.Event()
        self._lock = threading.Lock()
        self._report = AttackReport(self.name_, client)
        self.failure: str = ""
        """Why the attack ended early (the bus could not be joined), if it did."""

    def stop(self) -> None:
        """Ask the attack to end after the request in flight."""
        self._stop_event.set()

    def report(self) -> AttackReport:
        """A copy of what was sent and answered so far."""
        with self._lock:
            r = self._report
            return AttackReport(**{**r.__dict__, "errors": Counter(r.errors)})

    def run(self) -> None:
        t0 = time.monotonic()
        try:
            with open_session(self.bus) as session:
                try:
                    due = t0
                    while time.monotonic() - t0 < self.duration_s:
                        if self._stop_event.wait(max(0.0, due - time.monotonic())):
                            break
                        due += self.period_s
                        self.step(session)
                finally:
                    self.teardown(session)
        except zenoh.ZError as exc:
            self.failure = f"zenoh: {exc}"
        with self._lock:
            self._report.seconds = time.monotonic() - t0

    def teardown(self, session: zenoh.Session) -> None:
        """After the last step (nothing by default)."""

    def step(self, session: zenoh.Session) -> None:
        """One request (overridden)."""
        raise NotImplementedError

    def _count(self, **kw: int) -> None:
        with self._lock:
            for k, v in kw.items():
                setattr(self._report, k, getattr(self._report, k) + v)

    def _error(self, field_name: str) -> None:
        with self._lock:
            self._report.refused += 1
            self._report.errors[field_name] += 1


class _Uploader(Attack):
    """An attack by uploads of one vehicle (its own key, unique observation ids)."""

    timeout_s = 10.0

    def __init__(self, bus: BusConfig, duration_s: float, period_s: float, vehicle_id: str):
        super().__init__(bus, duration_s, period_s, vehicle_id)
        self.vehicle_id = vehicle_id
        self.next_id = 1
        self.batch_id = 0

    def take_ids(self, n: int) -> int:
        """The first of ``n`` new observation ids."""
        first = self.next_id
        self.next_id += n
        return first

    def upload(self, session: zenoh.Session, batch: ObservationBatch) -> None:
        """Send one batch and count its ack."""
        self._count(requests=1, observations=len(batch.obs))
        try:
            replies = query(
                session,
                keys.upload(self.vehicle_id),
                batch.to_bytes(),
                timeout=self.timeout_s,
                target=zenoh.QueryTarget.ALL,  # every ingest shard; its vehicle's answers
            )
        except zenoh.ZError:
            self._count(unanswered=1)
            return
        ack = None
        for _k, ok, _err in replies:
            if ok is not None:
                try:
                    ack = UploadAck.from_bytes(ok)
                except DecodeError:
                    continue
        if ack is None:
            self._count(unanswered=1)
            return
        self._count(replies=1)
        if ack.error is not None:
            self._error(ack.error.field)
            return
        self._count(
            accepted=len(ack.accepted), duplicates=len(ack.duplicates), rejected=len(ack.rejected)
        )
        with self._lock:
            for r in ack.rejected:
                self._report.errors[r.field] += 1

    def batch(self, pass_id: int, obs: Observations, sent_at: float | None = None):
        """The next batch of this vehicle."""
        self.batch_id += 1
        now = time.time() if sent_at is None else sent_at
        return ObservationBatch(self.vehicle_id, pass_id, self.batch_id, now, obs)


class StuckPass(_Uploader):
    """One pass whose pending rays never make a landmark (``restart`` or ``parked``, see
    :func:`stuck_pass_rays`), at ``rate`` observations/s."""

    def __init__(self, bus: BusConfig, duration_s: float, pattern: Pattern, rate: float = 8.0):
        self.name_ = pattern
        period = (3 if pattern == "restart" else 10) / rate
        super().__init__(bus, duration_s, period, f"attack-{pattern}")
        self.pattern: Pattern = pattern
        self.frame = EnuFrame(TOWN[0], TOWN[1], 20.0)
        self.rng = np.random.default_rng(0)
        self.k = 0

    def step(self, session: zenoh.Session) -> None:
        obs = stuck_pass_rays(self.frame, self.pattern, self.k, self.next_id, self.rng)
        self.take_ids(len(obs))
        self.k += 1
        self.upload(session, self.batch(1, obs))


class SpreadUpload(_Uploader):
    """Uploads of ``n_obs`` observations spread over the globe, one every ``period_s``
    (10,000 every 5 s: 2,000 obs/s, ingest's default per-vehicle limit)."""

    name_ = "spread"
    timeout_s = 30.0

    def __init__(
        self, bus: BusConfig, duration_s: float, n_obs: int = 10_000, period_s: float = 5.0
    ):
        super().__init__(bus, duration_s, period_s, "attack-spread")
        self.n_obs = n_obs
        self.rng = np.random.default_rng(0)

    def step(self, session: zenoh.Session) -> None:
        obs = spread_rays(self.n_obs, self.take_ids(self.n_obs), self.rng)
        self.upload(session, self.batch(self.batch_id + 1, obs))


class Newcomers(_Uploader):
    """A new made-up vehicle id every upload (what an unauthenticated client can do):
    ``n_obs`` observations at the town per upload, ``per_s`` uploads a second (issue 17:
    5,000 new vehicles in 40 s). Each id is within its own rate limit; every one is a
    vehicle the matcher has never seen (trust, probation, pending pools)."""

    name_ = "newcomers"

    def __init__(self, bus: BusConfig, duration_s: float, per_s: float = 125.0, n_obs: int = 4):
        super().__init__(bus, duration_s, 1.0 / per_s, "newcomer-0")
        self.n_obs, self.k = n_obs, 0

    def step(self, session: zenoh.Session) -> None:
        self.k += 1
        self.vehicle_id = f"newcomer-{self.k}"
        obs = fresh_observations(self.n_obs, self.take_ids(self.n_obs), self.k, *TOWN)
        self.upload(session, self.batch(1, obs))


class FutureDated(_Uploader):
    """Uploads sent in 2096 (``sent_at`` 4.0e9, inside the schema's range) of ``n_obs``
    rows at the town, half captured ``inside_s`` ahead of now (within ingest's default
    300 s clock-skew window), half a year ahead; one a second."""

    name_ = "future"

    def __init__(self, bus: BusConfig, duration_s: float, n_obs: int = 8, inside_s: float = 290):
        super().__init__(bus, duration_s, 1.0, "attack-future")
        self.n_obs, self.inside_s, self.at = n_obs, inside_s, TOWN

    def step(self, session: zenoh.Session) -> None:
        n = self.n_obs
        obs = fresh_observations(n, self.take_ids(n), self.batch_id, *self.at)
        now = time.time()
        t = np.where(np.arange(n) % 2 == 0, now + self.inside_s, now + 365 * 86400.0)
        obs = replace(obs, t=t)
        self.upload(session, self.batch(self.batch_id + 1, obs, sent_at=4.0e9))


class ForgedTokens(Attack):
    """Liveliness tokens with wildcards (:data:`FORGED_TOKENS`), all declared and then
    undeclared again every ``period_s`` (each declaration a PUT to every liveliness
    subscriber, e.g. the stage services' watch of their upstream)."""

    name_ = "tokens"

    def __init__(self, bus: BusConfig, duration_s: float, period_s: float = 0.5):
        super().__init__(bus, duration_s, period_s, "forged-tokens")
        self.keys = FORGED_TOKENS
        self.live: list[zenoh.LivelinessToken] = []

    def step(self, session: zenoh.Session) -> None:
        self.teardown(session)
        for k in self.keys:
            try:
                self.live.append(session.liveliness().declare_token(k))
                self._count(requests=1)
            except zenoh.ZError:
                self._error("declare")

    def teardown(self, session: zenoh.Session) -> None:
        for t in self.live:
            t.undeclare()
        self.live = []


class SnapshotQueries(Attack):
    """Snapshot queries, ``per_step`` at once (all sent before any reply is read) every
    ``period_s``, with no payload; error replies are counted by the field they name.

    - ``clients == 1`` (``snapshots``): all under the one id ``client`` on its snapshot
      key of ``tile`` (:func:`schemas.keys.map_snapshot_for`);
    - ``clients > 1`` (``sybil``): query ``k`` under the id ``<client>-<k mod clients>``,
      a new id each query until ``clients`` were used;
    - ``selector`` (``wildcard``): that selector for every query instead.
    """

    name_ = "snapshots"

    def __init__(
        self,
        bus: BusConfig,
        duration_s: float,
        period_s: float = 0.02,
        per_step: int = 10,
        clients: int = 1,
        client: str = "snapshot-client",
        tile: str | None = None,
        selector: str | None = None,
        timeout_s: float = 3.0,
    ):
        if selector is not None:
            self.name_ = "wildcard"
        elif clients > 1:
            self.name_ = "sybil"
        super().__init__(bus, duration_s, period_s, client if clients == 1 else f"{client}-*")
        self.per_step, self.clients, self.client = per_step, clients, client
        self.tile = tile or str(quadkeys_of([TOWN[0]], [TOWN[1]])[0])
        self.selector, self.timeout_s = selector, timeout_s
        self.k = 0

    def next_selector(self) -> str:
        """The key of the next query."""
        if self.selector is not None:
            return self.selector
        self.k += 1
        who = self.client if self.clients == 1 else f"{self.client}-{self.k % self.clients}"
        return keys.map_snapshot_for(who, self.tile)

    def step(self, session: zenoh.Session) -> None:
        pending = []
        for _ in range(self.per_step):
            self._count(requests=1)
            try:
                pending.append(
                    session.get(
                        self.next_selector(),
                        timeout=self.timeout_s,
                        consolidation=zenoh.ConsolidationMode.NONE,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
                )
            except zenoh.ZError:
                self._count(unanswered=1)
        for replies in pending:
            try:
                got = [(r.ok, r.err) for r in replies]
            except zenoh.ZError:
                self._count(unanswered=1)
                continue
            if not got:
                self._count(unanswered=1)
            for ok, err in got:
                self._count(replies=1)
                why = _refusal(
                    None if ok is None else ok.payload.to_bytes(),
                    None if err is None else err.payload.to_bytes(),
                )
                if why is not None:
                    self._error(why)


def _refusal(ok: bytes | None, err: bytes | None) -> str | None:
    """The field a reply refuses on (an error reply, or an upload ack with an error), or
    None for an answer (a snapshot, stats, a log reply)."""
    try:
        if err is not None:
            return ErrorReply.from_bytes(err).field
        if ok is not None and (ack_error := UploadAck.from_bytes(ok).error):
            return ack_error.field
    except DecodeError:  # not an ack: answered
        return "undecodable" if err is not None else None
    return None


def make_attack(name: str, bus: BusConfig, duration_s: float, fast: bool = False) -> Attack:
    """The attack ``name`` (one of :data:`ATTACK_NAMES`) at its default rate, or with
    ``fast`` (short tests) the stuck passes at 30 (restart) and 50 (parked) obs/s, so
    that they reach the matcher's budget and quarantine within seconds, spread uploads
    of 1,000 observations (not 10,000) and the Sybil client at up to 200 queries/s (not
    3,000, the rate of issue 17, which a shared test machine cannot take next to the
    rest). The snapshot attacks: ``snapshots`` up to 500 queries/s under one id (the
    per-client limit: 20/s after a burst of 200), ``sybil`` a new id each query, cycling
    over 100,000 ids (the publisher's ``max_clients``), ``wildcard`` 5 queries/s on
    ``hdmap/v1/**``."""
    if name == "restart":
        return StuckPass(bus, duration_s, "restart", 30.0 if fast else 8.0)
    if name == "parked":
        return StuckPass(bus, duration_s, "parked", 50.0 if fast else 8.0)
    if name == "spread":
        return SpreadUpload(bus, duration_s, 1_000 if fast else 10_000)
    if name == "tokens":
        return ForgedTokens(bus, duration_s)
    if name == "snapshots":
        return SnapshotQueries(bus, duration_s)
    if name == "sybil":
        step = (0.05, 10) if fast else (0.01, 30)
        return SnapshotQueries(bus, duration_s, *step, clients=100_000, client="sybil")
    if name == "wildcard":
        return SnapshotQueries(
            bus, duration_s, 0.2, 1, client="wildcard-client", selector=f"{keys.ROOT}/**"
        )
    if name == "future":
        return FutureDated(bus, duration_s)
    if name == "newcomers":
        return Newcomers(bus, duration_s, 25.0 if fast else 125.0)
    raise ValueError(f"unknown attack {name!r}; one of {', '.join(ATTACK_NAMES)}")


def stop_all(attacks: list[Attack], timeout_s: float = 40.0) -> None:
    """Stop every attack and wait for its thread (bounded: each request has a timeout)."""
    for a in attacks:
        a.stop()
    deadline = time.monotonic() + timeout_s
    for a in attacks:
        if a.is_alive():
            a.join(max(0.1, deadline - time.monotonic()))
