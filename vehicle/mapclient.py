"""The vehicle's copy of the map: tiles around it, kept current by deltas.

``update_position`` subscribes to the deltas of the tiles within ``radius_m`` and
drops the others. A tile starts with its snapshot; each delta applies only on top
of the version it names (``from_version``): an older one is ignored, a newer one
means a gap and the tile is re-fetched. Deltas that arrive while a snapshot is in
flight are buffered and applied after it; one still ahead of that (fresher)
snapshot is dropped rather than fetched for again (the publisher commits a version
before publishing it, so it is none of its history; a real gap shows again on the
next delta). At most one fetch per tile is queued; a failed one (no publisher
answered) is retried on the next delta. Zenoh callbacks only queue; the
client's own thread applies, so ``near()`` reads a consistent map.
``update_position``, ``follow`` and ``unfollow`` may be called from several threads
(a GPS thread and the application): subscription changes are serialised, so each
followed tile has exactly one subscription.

Snapshots are asked for under the client's id (``client_id``, the vehicle id:
``hdmap/v1/map/<tile>/by/<id>``, the only snapshot key a vehicle may query in secured
mode), or on the anonymous ``hdmap/v1/map/<tile>`` without one. The publisher limits the
queries of each client (``services/publisher/limits.py``): a snapshot refused with
``rate`` or ``busy`` is asked for again after the error's ``retry_after_s``
(:func:`retry_delay`: at least :data:`MIN_RETRY_S`, at most ``max_retry_s``, plus up to
:data:`RETRY_JITTER` of it at random so that refused clients do not come back together),
scheduled on the client's own thread; the tile stays "fetching" meanwhile (its deltas are
buffered, no other fetch is queued) and the refusal is counted in
``stats.snapshots_refused``.
"""

from __future__ import annotations

import heapq
import logging
import queue
import random
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.tiles import DEFAULT_ZOOM, tiles_around
from hdmap.runtime.bus import query
from schemas import DecodeError, ErrorReply, MapDelta, MapSnapshot, keys
from schemas.codec import valid_id
from schemas.map import MapLandmarks, as_map_landmarks

log = logging.getLogger(__name__)

RETRIED_CODES = ("rate", "busy")
"""Error codes of a snapshot refusal that passes by itself: the fetch is retried."""
MIN_RETRY_S = 0.05
"""Least wait before a refused snapshot is asked for again (also when the error gives none)."""
RETRY_JITTER = 0.25
"""A refused fetch waits up to this fraction more than told, at random."""


def retry_delay(retry_after_s: float, u: float, max_s: float = 60.0) -> float:
    """Seconds before a refused snapshot is asked for again: ``retry_after_s`` clamped to
    ``[MIN_RETRY_S, max_s]``, times ``1 + RETRY_JITTER * u`` for ``u`` in [0, 1).

    >>> retry_delay(2.0, 0.0), retry_delay(2.0, 0.5), retry_delay(0.0, 0.0), retry_delay(1e4, 0.0)
    (2.0, 2.25, 0.05, 60.0)
    """
    base = min(max(retry_after_s, MIN_RETRY_S), max_s)
    return base * (1.0 + RETRY_JITTER * u)


def _refusal(err: bytes) -> ErrorReply | None:
    """The error reply if it is a refusal that passes by itself (:data:`RETRIED_CODES`)."""
    try:
        e = ErrorReply.from_bytes(err)
    except DecodeError:
        return None
    return e if e.code in RETRIED_CODES else None


@dataclass
class TileCopy:
    version: int = -1
    """-1 until the snapshot arrived."""
    rows: dict[int, MapLandmarks] = field(default_factory=dict)
    buffered: list[MapDelta] = field(default_factory=list)
    fetching: bool = False
    """A snapshot fetch is queued, in flight, or scheduled again after a refusal."""
    retry_at: float | None = None
    """When the refused snapshot is asked for again (monotonic s); None: no retry pending."""


@dataclass
class ClientStats:
    deltas_applied: int = 0
    deltas_stale: int = 0
    gaps: int = 0
    ahead_of_snapshot: int = 0
    """Buffered deltas dropped because a fresher snapshot was behind their from_version."""
    snapshots: int = 0
    snapshots_refused: int = 0
    """Snapshot fetches the publisher refused with ``rate`` or ``busy`` (each retried later)."""
    subscribed: int = 0
    dropped: int = 0
    resyncs: int = 0
    """Every followed tile refetched because a publisher (re)appeared on the bus: after a
    publisher restart or a reconnection, deltas may have been missed on tiles that do not
    change again (no later delta would reveal the gap)."""


class MapClient:
    """Local map of the tiles around a moving vehicle."""

    def __init__(
        self,
        session: zenoh.Session,
        radius_m: float = 500.0,
        zoom: int = DEFAULT_ZOOM,
        snapshot_timeout: float = 5.0,
        client_id: str | None = None,
        max_retry_s: float = 60.0,
    ):
        """``client_id``: the id snapshots are asked for under (the vehicle id; None: the
        anonymous key). ``max_retry_s``: the longest wait before a refused snapshot is
        asked for again, whatever the publisher says."""
        if client_id is not None and not valid_id(client_id):
            raise ValueError(f"client_id {client_id!r}: 1-64 characters of [A-Za-z0-9_.-]")
        self._session = session
        self.radius_m = radius_m
        self.zoom = zoom
        self._timeout = snapshot_timeout
        self.client_id = client_id
        self.max_retry_s = max_retry_s
        self._rng = random.Random()
        self._retries: list[tuple[float, str]] = []
        """Heap of (due, tile) of refused fetches (the worker's only)."""
        self._markers: list[threading.Event] = []
        """``wait_idle`` markers reached while a refused fetch waits (the worker's only)."""
        self._tiles: dict[str, TileCopy] = {}
        self._subs: dict[str, zenoh.Subscriber] = {}
        self._lock = threading.Lock()
        """Guards the tile copies (the worker applies, callers read)."""
        self._subs_lock = threading.RLock()
        """Serialises subscription changes (``_subs`` and the subscribe/drop counts)."""
        self._inbox: queue.Queue[tuple[str, str, bytes | threading.Event] | None] = queue.Queue()
        self.stats = ClientStats()
        self._thread = threading.Thread(target=self._run, name="mapclient", daemon=True)
        self._thread.start()

        def on_alive(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                self._inbox.put(("resync", "", b""))

        self._alive = session.liveliness().declare_subscriber(
            keys.alive("publisher", "*", "*"), on_alive
        )

    # -- subscriptions -------------------------------------------------------------------

    def update_position(self, lat: float, lon: float) -> list[str]:
        """Follow the vehicle: subscribe to near tiles, drop far ones; the near tiles."""
        want = set(tiles_around(lat, lon, self.radius_m, self.zoom))
        with self._subs_lock:
            for tile in sorted(want - set(self._subs)):
                self.follow(tile)
            for tile in sorted(set(self._subs) - want):
                self.unfollow(tile)
        return sorted(want)

    def follow(self, tile: str) -> None:
        with self._subs_lock:
            if tile in self._subs:
                return
            with self._lock:
                self._tiles[tile] = TileCopy(fetching=True)

            def cb(sample: zenoh.Sample, tile: str = tile) -> None:
                self._inbox.put(("delta", tile, sample.payload.to_bytes()))

            self._subs[tile] = self._session.declare_subscriber(keys.map_delta(tile), cb)
            self.stats.subscribed += 1
            self._inbox.put(("fetch", tile, b""))

    def unfollow(self, tile: str) -> None:
        with self._subs_lock:
            sub = self._subs.pop(tile, None)
            if sub is None:
                return
            sub.undeclare()
            with self._lock:
                self._tiles.pop(tile, None)
            self.stats.dropped += 1

    def close(self) -> None:
        self._alive.undeclare()
        with self._subs_lock:
            for tile in list(self._subs):
                self._subs.pop(tile).undeclare()
        self._inbox.put(None)
        self._thread.join(timeout=5)

    # -- worker ----------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            wait = self._retries[0][0] - time.monotonic() if self._retries else None
            try:
                item = self._inbox.get(timeout=None if wait is None else max(0.0, wait))
            except queue.Empty:
                item = ("retry", "", b"")
            if item is None:
                return
            self._do(*item)
            self._retry_due()
            if self._markers and not self._retry_pending():
                for m in self._markers:
                    m.set()
                self._markers.clear()

    def _do(self, kind: str, tile: str, payload: bytes | threading.Event) -> None:
        try:
            if isinstance(payload, threading.Event):
                self._markers.append(payload)  # set once no refused fetch waits (_run)
            elif kind == "fetch":
                self._fetch(tile)
            elif kind == "resync":
                self._resync()
            elif kind == "delta":
                self._on_delta(tile, payload)
        except (DecodeError, zenoh.ZError) as exc:
            log.warning("map client: %s on tile %s: %s", kind, tile, exc)

    def _retry_due(self) -> None:
        """Fetch again the refused snapshots whose wait is over (each only if it is still
        the tile's pending retry: unfollowed, or fetched since by a resync, it is not)."""
        now = time.monotonic()
        while self._retries and self._retries[0][0] <= now:
            due, tile = heapq.heappop(self._retries)
            with self._lock:
                copy = self._tiles.get(tile)
                current = copy is not None and copy.retry_at == due
            if current:
                self._do("fetch", tile, b"")

    def _resync(self) -> None:
        with self._lock:
            tiles = sorted(self._tiles)
            for t in tiles:
                self._tiles[t].fetching = True  # deltas arriving meanwhile are buffered
        self.stats.resyncs += 1
        for t in tiles:
            self._fetch(t)

    def _retry_pending(self) -> bool:
        """Whether a followed tile waits to ask for its refused snapshot again."""
        with self._lock:
            return any(c.retry_at is not None for c in self._tiles.values())

    def snapshot_key(self, tile: str) -> str:
        """The key this client asks for ``tile``'s snapshot on."""
        if self.client_id is None:
            return keys.map_snapshot(tile)
        return keys.map_snapshot_for(self.client_id, tile)

    def _fetch(self, tile: str) -> None:
        snap, refused = None, None
        for _k, ok, err in query(self._session, self.snapshot_key(tile), timeout=self._timeout):
            if ok is not None:
                snap = MapSnapshot.from_bytes(ok)
            elif err is not None:
                refused = _refusal(err) or refused
        with self._lock:
            copy = self._tiles.get(tile)
            if copy is None:
                return
            copy.retry_at = None
            if snap is None and refused is not None:  # ask again later; still fetching
                self.stats.snapshots_refused += 1
                delay = retry_delay(refused.retry_after_s, self._rng.random(), self.max_retry_s)
                copy.retry_at = time.monotonic() + delay
                heapq.heappush(self._retries, (copy.retry_at, tile))
                return
            copy.fetching = False
            if snap is None:
                copy.version = -1  # no publisher answered: try again on the next delta
                return
            self.stats.snapshots += 1
            copy.version = snap.version
            copy.rows = {
                int(i): snap.landmarks.take(np.array([k])) for k, i in enumerate(snap.landmarks.id)
            }
            pending, copy.buffered = copy.buffered, []
        for d in sorted(pending, key=lambda d: d.from_version):
            self._apply(tile, d, after_snapshot=True)

    def _on_delta(self, tile: str, payload: bytes) -> None:
        self._apply(tile, MapDelta.from_bytes(payload))

    def _apply(self, tile: str, d: MapDelta, after_snapshot: bool = False) -> None:
        refetch = False
        with self._lock:
            copy = self._tiles.get(tile)
            if copy is None:
                return
            if copy.version < 0:
                copy.buffered.append(d)
                refetch = not copy.fetching
            elif d.to_version <= copy.version:
                self.stats.deltas_stale += 1
            elif d.from_version != copy.version and after_snapshot:
                self.stats.ahead_of_snapshot += 1
                log.warning(
                    "map client: tile %s: delta %d->%d ahead of snapshot %d, dropped",
                    tile,
                    d.from_version,
                    d.to_version,
                    copy.version,
                )
            elif d.from_version != copy.version:
                self.stats.gaps += 1
                copy.version = -1
                copy.buffered = [d]
                refetch = not copy.fetching
            else:
                for k, i in enumerate(d.upserts.id):
                    copy.rows[int(i)] = d.upserts.take(np.array([k]))
                for i in d.removed.id:
                    copy.rows.pop(int(i), None)
                copy.version = d.to_version
                self.stats.deltas_applied += 1
            if refetch:
                copy.fetching = True
        if refetch:
            self._inbox.put(("fetch", tile, b""))

    # -- queries -----------------------------------------------------------------------------

    def versions(self) -> dict[str, int]:
        with self._lock:
            return {t: c.version for t, c in self._tiles.items()}

    def landmarks(self) -> MapLandmarks:
        """Every landmark held, over all followed tiles, with its facing
        (``facing_deg``, ``facing_sigma_deg``: the direction the sign is seen from, degrees
        clockwise from North, and its standard error; 0 = unknown; :meth:`MapLandmarks.
        facing` gives NaN for unknown)."""
        with self._lock:
            rows = [r for c in self._tiles.values() for r in c.rows.values()]
        return MapLandmarks.concat([as_map_landmarks(r) for r in rows])

    def near(self, lat: float, lon: float, radius_m: float) -> MapLandmarks:
        """Landmarks within ``radius_m`` (horizontal) of a point."""
        lm = self.landmarks()
        if len(lm) == 0:
            return lm
        enu = EnuFrame(lat, lon, 0.0).from_geodetic(lm.lat, lm.lon, lm.h)
        return lm.take(np.hypot(enu[:, 0], enu[:, 1]) <= radius_m)

    def wait_idle(self, timeout: float = 5.0) -> bool:
        """Until everything queued before this call is applied and no refused snapshot
        waits to be asked for again (bounded); whether it was."""
        marker = threading.Event()
        self._inbox.put(("marker", "", marker))
        return marker.wait(timeout)
