"""Ingest: vehicles upload by request/reply; the ack means "durably recorded".

Per upload (``hdmap/v1/upload/<vehicle_id>`` queryable):

1. rate limits per vehicle (:mod:`services.ingest.ratelimit`): an upload over the
   vehicle's uploads/s is refused before it is decoded, a batch over its
   observations/s after; both with ``error.field == "rate"`` and ``retry_after_s``;
2. decode and validate (:class:`schemas.ObservationBatch`); a broken batch is
   answered with an :class:`schemas.UploadAck` carrying the error, bad rows are
   rejected one by one with field and reason (a class not in the deployment's sign
   catalogue, ``IngestConfig.catalog``: ``obs.sign_class``, naming the code); admission
   policy (timestamps, vehicle id matching the key, pass ids the pipeline can carry)
   rejects more;
   a well-formed batch of a vehicle ingest has never recorded anything from takes a
   token of the budget of new vehicles shared by all (``new_vehicles_per_s``): past it,
   ``error.field == "vehicle.new"`` with ``retry_after_s``, so a client inventing
   vehicle ids adds load only at that rate;
3. drop duplicates by (vehicle, observation id): a retried batch is acknowledged
   again but recorded once;
4. route each new observation to the tile of its expected target point and each new
   absence (``ObservationBatch.absences``: a mapped landmark the pass did not detect;
   deduplicated by (vehicle, pass, landmark), admitted in the observations' time window)
   to its landmark's home tile, and append one :class:`schemas.ObsGroup` entry per tile
   to the obs log, in the same SQLite transaction as the dedup rows;
5. commit, then reply the ack, then publish the entries on ``hdmap/v1/obs/<tile>``.

Uploads that arrive together are committed in one transaction (one fsync for many).
Every refused upload or row is counted in ``Stats.rejected`` by reason (``batch.<field>``,
``obs.<column>``, ``absences.<column>``, ``rate_limited``, ``vehicle.new``).

Storage: a failed transaction (disk full, read-only) is answered ``error.field ==
"storage"`` with ``retry_after_s`` :data:`STORAGE_RETRY_S` (transient: it passes by
itself). A corrupt database (:class:`hdmap.runtime.store.DatabaseCorrupt`) is permanent:
ingest stops writing to the file (more writes could spread the damage), answers this and
every later upload with a ``storage`` refusal marked ``permanent`` and ``retry_after_s``
:data:`CORRUPT_RETRY_S`, counts them in ``counters.corrupt_refusals`` (with gauge
``database_corrupt`` = 1), and keeps serving stats; at its next start the check at open
stops it (:mod:`hdmap.runtime.service`).
"""

from __future__ import annotations

import itertools
import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import zenoh

from hdmap.geo.signs import CATALOG, SignCatalog, SignCatalogError
from hdmap.geo.tiles import DEFAULT_TARGET_RANGE_M, route_rays
from hdmap.runtime.config import ConfigError
from hdmap.runtime.log_out import LogServer, LogWriter
from hdmap.runtime.ratelimit import MAX_RETRY_AFTER_S
from hdmap.runtime.retention import LogRetention
from hdmap.runtime.service import Item, Service, ServiceOptions
from hdmap.runtime.shards import shard_of
from hdmap.runtime.store import DatabaseCorrupt, Meta, StorageError, u64_to_i64
from hdmap.runtime.stream import STAGE_KEYS
from schemas import DecodeError, ObservationBatch, ObsGroup, UploadAck, keys
from schemas.codec import valid_id
from schemas.ids import home_tile
from schemas.messages import MAX_BATCH
from services.ingest.admission import (
    AdmissionPolicy,
    admit,
    admit_absences,
    check_header,
    oldest_admitted,
)
from services.ingest.ratelimit import RateLimit, VehicleLimiter

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IngestConfig:
    max_batch: int = MAX_BATCH
    default_range_m: float = DEFAULT_TARGET_RANGE_M
    catalog: str = ""
    """Sign catalogue file of the deployment (TOML, format in ``deploy/signs.toml``): the
    classes an upload may name, besides the defaults of :data:`hdmap.geo.signs.CATALOG`
    (""). A relative path is read from the service's working directory."""
    policy: AdmissionPolicy = field(default_factory=AdmissionPolicy)
    rate_limit: RateLimit = field(default_factory=RateLimit)


def load_catalog(path: str) -> SignCatalog:
    """The sign catalogue ``IngestConfig.catalog`` names; a bad file is a
    :class:`ConfigError` naming the key, the file, the entry and the field."""
    if not path:
        return CATALOG
    try:
        return SignCatalog.from_toml(path)
    except SignCatalogError as exc:
        raise ConfigError(f"ingest.catalog: {exc}") from exc


_NO_IDS = np.zeros(0, np.uint64)

UNKNOWN_VEHICLE = "unknown"
"""``UploadAck.vehicle_id`` when the sender is not known (bad key, storage failure)."""

STORAGE_RETRY_S = 5.0
"""``retry_after_s`` of a transient storage refusal (disk full, read-only data dir)."""

CORRUPT_RETRY_S = 300.0
"""``retry_after_s`` of the permanent refusal on a corrupt database: how often a vehicle
may probe whether an operator has repaired it (vehicles that do not read ``permanent``
also slow down to this)."""


@dataclass
class _Pending:
    """An upload decoded and staged in the current transaction, waiting for its ack."""

    item: Item
    ack: UploadAck


class _Horizon:
    """The newest capture time admitted (the fleet's own clock, meta ``horizon``), kept
    with the transaction that admitted it."""

    def __init__(self, meta: Meta):
        self._meta = meta
        got = meta.get("horizon")
        self.value = float(got) if got is not None else -float("inf")
        self._staged: float | None = None

    def admitted(self, t: float) -> None:
        """Observations captured up to ``t`` were admitted (inside the transaction)."""
        if t > (self.value if self._staged is None else self._staged):
            self._meta.set("horizon", repr(t))
            self._staged = t

    def on_commit(self) -> None:
        if self._staged is not None:
            self.value = self._staged
        self._staged = None

    def on_rollback(self) -> None:
        self._staged = None


class IngestService(Service):
    name = "ingest"
    stops_on_corruption = False  # it refuses uploads as permanent instead (module docstring)

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS seen (
        vehicle TEXT NOT NULL, obs_id INTEGER NOT NULL, t REAL NOT NULL DEFAULT 0,
        PRIMARY KEY (vehicle, obs_id)) WITHOUT ROWID;
    CREATE TABLE IF NOT EXISTS seen_absence (
        vehicle TEXT NOT NULL, pass_id INTEGER NOT NULL, landmark_id INTEGER NOT NULL,
        t REAL NOT NULL, PRIMARY KEY (vehicle, pass_id, landmark_id)) WITHOUT ROWID;
    CREATE INDEX IF NOT EXISTS seen_absence_t ON seen_absence(t);
    """

    PRUNE_EVERY_S = 60.0
    """How often the ids past the admission window are forgotten (:meth:`prune_seen`)."""
    PRUNE_CHUNK = 20_000
    """Ids deleted per transaction (uploads are answered between them)."""

    def __init__(self, opts: ServiceOptions, config: IngestConfig | None = None):
        config = config or IngestConfig()
        catalog = load_catalog(config.catalog)  # before the data dir: a bad file touches nothing
        super().__init__(opts)
        self.config = config
        self.catalog = catalog
        """Sign classes an upload may name; rows of other classes are refused one by one."""
        if config.catalog:
            log.info("ingest: sign catalogue %s (%d classes)", config.catalog, len(catalog))
        self.db.executescript(self.SCHEMA)
        if "t" not in {r[1] for r in self.db.execute("PRAGMA table_info(seen)")}:
            # ids recorded before their times were: kept one admission window from now
            self.db.execute(f"ALTER TABLE seen ADD COLUMN t REAL NOT NULL DEFAULT {time.time()}")
        self.db.execute("CREATE INDEX IF NOT EXISTS seen_t ON seen(t)")
        self.wall: Callable[[], float] = time.time
        """The wall clock admission compares capture times with (injectable)."""
        self._horizon = _Horizon(Meta(self.db))
        self.writer = LogWriter(self.db, "obs", self.instance)
        self.retention = LogRetention(self.db, "obs", self.instance, opts.retention)
        self._log_server: LogServer | None = None
        self.limiter = VehicleLimiter(self.config.rate_limit)
        self._admitted: list[str] = []
        """Vehicles with observations staged in the open transaction (known once it commits)."""
        self.corrupt: DatabaseCorrupt | None = None
        """Set once a transaction met corruption: nothing more is written, uploads refused."""

    def setup(self) -> None:
        i, n = self.opts.shard
        self.serve(
            keys.upload(keys.ANY), "upload", lambda key: shard_of(keys.last_chunk(key), n) == i
        )
        self._log_server = LogServer(self.session, self.db_path, "obs", self.instance)
        self.retention.wire(self)
        self.every(self.PRUNE_EVERY_S, lambda _now: self.prune_seen())

    def teardown(self) -> None:
        if self._log_server is not None:
            self._log_server.close()

    def handle(self, items: list[Item]) -> None:
        if self.corrupt is None:
            self.retention.take(self, items)
        uploads = [it for it in items if it.kind == "upload" and it.query is not None]
        if self.corrupt is not None:
            self._refuse_corrupt(uploads)
            return
        staged: list[_Pending] = []
        entries = []
        self._admitted = []
        try:
            with self.transaction(self.participants):
                for it in uploads:
                    ack, new_entries = self._stage(it)
                    staged.append(_Pending(it, ack))
                    entries += new_entries
                self.count("log_entries", len(entries))
        except DatabaseCorrupt as exc:
            log.error(
                "ingest: %s; refusing every upload as permanent until the file is restored "
                "and ingest restarted",
                exc,
            )
            self.count("storage_errors")
            self.corrupt = exc
            self._refuse_corrupt(uploads)
            return
        except StorageError as exc:
            log.error("ingest: %s", exc)
            self.count("storage_errors")
            err = DecodeError("storage", f"not recorded, retry later ({exc})")
            for it in uploads:
                ack = UploadAck(_sender(it), 0, _NO_IDS, error=err, retry_after_s=STORAGE_RETRY_S)
                self._reply(it, ack)
            return
        for v in self._admitted:
            self.limiter.admitted(v)
        self._admitted = []
        for p in staged:
            self._reply(p.item, p.ack)
        for e in entries:
            self.pubs.put(STAGE_KEYS["obs"](e.tile), e.to_bytes())

    def _refuse_corrupt(self, uploads: list[Item]) -> None:
        """Answer uploads with the permanent refusal of a corrupt database (nothing read or
        written; the ack names the fault, not the server's file path, which is logged)."""
        assert self.corrupt is not None
        err = DecodeError(
            "storage",
            f"not recorded: ingest's database is corrupt ({self.corrupt.cause}); permanent "
            "until an operator restores it",
        )
        self.count("corrupt_refusals", len(uploads))
        for it in uploads:
            ack = UploadAck(
                _sender(it), 0, _NO_IDS, error=err, retry_after_s=CORRUPT_RETRY_S, permanent=True
            )
            self._reply(it, ack)

    def _reply(self, it: Item, ack: UploadAck) -> None:
        assert it.query is not None
        try:
            it.query.reply(it.query.key_expr, ack.to_bytes())
        except zenoh.ZError as exc:  # the querier is gone: it resends, retries are safe
            log.warning("ingest: cannot reply on %s: %s", it.key, exc)
            self.count("reply_errors")
        finally:
            it.query.drop()

    def _stage(self, it: Item):
        """Decode, validate, dedupe and append one upload (inside the transaction)."""
        self.count("uploads")
        key_vehicle = keys.last_chunk(it.key)
        if not valid_id(key_vehicle):
            self.reject("batch.key")
            err = DecodeError(
                "key",
                f"{key_vehicle[:80]!r} (last chunk of {keys.upload('<vehicle_id>')}) is not a "
                "vehicle id: 1-64 characters of [A-Za-z0-9_.-]",
            )
            return UploadAck(UNKNOWN_VEHICLE, 0, _NO_IDS, error=err), []
        wait = self.limiter.upload(key_vehicle)
        if wait > 0:
            lim = self.config.rate_limit
            return self._rate_limited(
                key_vehicle, 0, wait, f"more than {lim.uploads_per_s:g} uploads/s"
            ), []
        try:
            batch, rejected = ObservationBatch.from_bytes_partial(
                it.payload, self.config.max_batch, self.catalog
            )
            if batch.vehicle_id != key_vehicle:
                raise DecodeError(
                    "vehicle_id",
                    f"{batch.vehicle_id!r} does not match the upload key {key_vehicle!r}",
                )
            check_header(batch)
        except DecodeError as exc:
            self.reject(f"batch.{exc.field}")
            return UploadAck(key_vehicle, 0, _NO_IDS, error=exc), []
        wait = self.limiter.newcomer(key_vehicle, self._recorded)
        if wait > 0:
            self.reject("vehicle.new")
            wait = min(max(wait, 0.001), MAX_RETRY_AFTER_S)
            lim = self.config.rate_limit
            err = DecodeError(
                "vehicle.new",
                f"vehicle {key_vehicle!r} is new and new vehicles are admitted at "
                f"{lim.new_vehicles_per_s:g}/s; retry after {wait:.3g} s",
            )
            return UploadAck(
                key_vehicle, batch.batch_id, _NO_IDS, error=err, retry_after_s=wait
            ), []
        n_rows = len(batch.obs) + len(batch.absences) + len(rejected)
        wait = self.limiter.observations(key_vehicle, n_rows)
        if wait > 0:
            self.count("rate_limited_obs", n_rows)
            lim = self.config.rate_limit
            why = f"more than {lim.observations_per_s:g} observations/s"
            return self._rate_limited(key_vehicle, batch.batch_id, wait, why), []
        self.count("received", n_rows)
        all_tiles = route_rays(
            batch.obs.lat,
            batch.obs.lon,
            batch.obs.h,
            batch.obs.direction,
            batch.obs.range_m,
            self.opts.zoom,
            self.config.default_range_m,
        )
        keep, more = admit(batch.obs, self.config.policy, self.wall(), all_tiles, self.horizon)
        obs = batch.obs.take(keep) if not keep.all() else batch.obs
        rejected += more
        ab_tiles = np.array(
            [home_tile(int(i), self.opts.zoom) for i in batch.absences.landmark_id], dtype=object
        ).astype(str)
        ab_keep, more = admit_absences(
            batch.absences, self.config.policy, self.wall(), ab_tiles, self.horizon
        )
        absences, ab_tiles = batch.absences.take(ab_keep), ab_tiles[ab_keep]
        rejected += more
        for reason, n in Counter(r.field for r in rejected).items():
            self.reject(reason, n)

        ids = obs.obs_id
        dup = self._seen(batch.vehicle_id, ids)
        new = obs.take(~dup) if dup.any() else obs
        self.db.executemany(
            "INSERT INTO seen(vehicle, obs_id, t) VALUES (?, ?, ?)",
            zip(
                itertools.repeat(batch.vehicle_id),
                u64_to_i64(new.obs_id).tolist(),
                new.t.tolist(),
                strict=False,
            ),
        )
        if len(new):
            self._horizon.admitted(float(new.t.max()))
        self.count("accepted", len(new))
        self.count("duplicates", int(dup.sum()))
        if len(new):
            self._admitted.append(batch.vehicle_id)
        ab_dup = self._seen_absences(batch.vehicle_id, batch.pass_id, absences.landmark_id)
        ab_new, ab_tiles = absences.take(~ab_dup), ab_tiles[~ab_dup]
        self.db.executemany(
            "INSERT INTO seen_absence(vehicle, pass_id, landmark_id, t) VALUES (?, ?, ?, ?)",
            zip(
                itertools.repeat(batch.vehicle_id),
                itertools.repeat(int(batch.pass_id)),
                u64_to_i64(ab_new.landmark_id).tolist(),
                ab_new.t.tolist(),
                strict=False,
            ),
        )
        self.count("absences_accepted", len(ab_new))
        self.count("absences_duplicates", int(ab_dup.sum()))
        entries = []
        tiles = all_tiles[keep][~dup]
        for tile in np.unique(np.concatenate([tiles.astype(str), ab_tiles])):
            group = ObsGroup(
                batch.vehicle_id,
                batch.pass_id,
                batch.batch_id,
                time.time(),
                new.take(tiles == tile),
                ab_new.take(ab_tiles == tile),
            )
            entries.append(self.writer.append(str(tile), group.to_bytes()))
        ack = UploadAck(
            batch.vehicle_id,
            batch.batch_id,
            ids,
            duplicates=ids[dup],
            rejected=rejected,
            absences=len(absences),
        )
        return ack, entries

    def _rate_limited(self, vehicle: str, batch_id: int, wait: float, why: str) -> UploadAck:
        """The ack of an upload refused by a rate limit (nothing recorded; resend later)."""
        self.reject("rate_limited")
        wait = min(max(wait, 0.001), MAX_RETRY_AFTER_S)
        err = DecodeError("rate", f"vehicle {vehicle!r} sends {why}; retry after {wait:.3g} s")
        return UploadAck(vehicle, batch_id, _NO_IDS, error=err, retry_after_s=wait)

    def _recorded(self, vehicle: str) -> bool:
        """Whether ingest has recorded an observation of ``vehicle`` (committed, or staged
        in the current transaction)."""
        row = self.db.execute("SELECT 1 FROM seen WHERE vehicle=? LIMIT 1", (vehicle,))
        return row.fetchone() is not None

    @property
    def horizon(self) -> float:
        """The newest capture time admitted (committed)."""
        return self._horizon.value

    @property
    def participants(self) -> list:
        """What follows an upload transaction's outcome: the log writer, the horizon."""
        return [self.writer, self._horizon]

    def prune_seen(self) -> int:
        """Forget the ids whose capture time is past the admission window (with a minute to
        spare): an upload that sends one again is refused as too old before its ids are
        looked up, so the dedup table stays one window deep whatever the fleet's history.
        How many ids went (counted ``seen_pruned``)."""
        before = oldest_admitted(self.config.policy, self.wall(), self.horizon) - 60.0
        gone = 0
        for _ in range(10_000):  # bounded: PRUNE_CHUNK ids a transaction
            with self.transaction():
                n = self.db.execute(
                    "DELETE FROM seen WHERE (vehicle, obs_id) IN "
                    "(SELECT vehicle, obs_id FROM seen WHERE t < ? LIMIT ?)",
                    (before, self.PRUNE_CHUNK),
                ).rowcount
                n += self.db.execute(
                    "DELETE FROM seen_absence WHERE (vehicle, pass_id, landmark_id) IN "
                    "(SELECT vehicle, pass_id, landmark_id FROM seen_absence WHERE t < ? LIMIT ?)",
                    (before, self.PRUNE_CHUNK),
                ).rowcount
                self.count("seen_pruned", n)
            gone += n
            if n < self.PRUNE_CHUNK:
                break
        return gone

    def _seen(self, vehicle: str, ids: np.ndarray) -> np.ndarray:
        """Which of a vehicle's observation ids ingest recorded before."""
        return _recorded(
            self.db, "SELECT obs_id FROM seen WHERE vehicle=? AND obs_id", [vehicle], ids
        )

    def _seen_absences(self, vehicle: str, pass_id: int, ids: np.ndarray) -> np.ndarray:
        """Which of a pass's absences (by landmark id) ingest recorded before."""
        sql = "SELECT landmark_id FROM seen_absence WHERE vehicle=? AND pass_id=? AND landmark_id"
        return _recorded(self.db, sql, [vehicle, int(pass_id)], ids)

    def extra_counters(self) -> dict[str, float]:
        return {
            "log_head_gseq": self.writer.gseq,
            "database_corrupt": int(self.corrupt is not None),
        }


def _recorded(db, select: str, head: list, ids: np.ndarray) -> np.ndarray:
    """Per u64 id, whether ``select`` (ending in the id column, completed with ``IN
    (...)``) finds it with the parameters ``head``, asked 900 ids at a time."""
    if ids.size == 0:
        return np.zeros(0, bool)
    signed = u64_to_i64(ids).tolist()
    found: set[int] = set()
    for s in range(0, len(signed), 900):
        part = signed[s : s + 900]
        rows = db.execute(f"{select} IN ({','.join('?' * len(part))})", [*head, *part])
        found.update(r[0] for r in rows)
    return np.fromiter((x in found for x in signed), bool, len(signed))


def _sender(it: Item) -> str:
    """The vehicle id of an upload's key (``unknown`` if it is not an id)."""
    vehicle = keys.last_chunk(it.key)
    return vehicle if valid_id(vehicle) else UNKNOWN_VEHICLE
