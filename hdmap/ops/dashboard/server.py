"""``hdmap dashboard``'s server: the live map and the services' health, on one web page.

Wiring (one Zenoh session, one HTTP server, three threads of its own):

- a :class:`vehicle.mapclient.MapClient` follows the area's tiles (each tile's snapshot,
  then its deltas on ``hdmap/v1/map/<tile>/delta``; gaps refetched, a restarted
  publisher resynced, refused snapshots retried: all the map client's). Without an area
  the dashboard subscribes to every tile's deltas (``hdmap/v1/map/*/delta``) and follows
  each tile that publishes one (at most :data:`~hdmap.ops.dashboard.geometry.
  MAX_AREA_TILES`): tiles that do not change after it started are not shown.
- the *map thread* compares the client's tile versions every ``refresh_s``; when one
  moved it hands the landmarks to :class:`~hdmap.ops.dashboard.view.MapView` and pushes
  the change (features of new and changed landmarks, removed ids) to every page;
- the *stats thread* asks every live service for its stats
  (:func:`hdmap.ops.status.collect`) every ``stats_interval_s`` and pushes the health
  panel's rows (:func:`~hdmap.ops.dashboard.geometry.service_row`: backlog, accepted and
  rejected counts, their rates);
- a ``ThreadingHTTPServer`` serves the page and MapLibre GL JS from ``static/`` (shipped
  in the package: no CDN, no tile server), ``/api/landmarks`` (GeoJSON),
  ``/api/stats``, ``/api/tiles``, ``/api/history/<id>``, and ``/events``: server-sent
  events (``reset`` on connecting: the whole map and the latest stats; then ``delta``,
  ``tiles`` and ``stats``). A page that reads too slowly (its queue of
  ``client_queue`` events full) is disconnected; its EventSource reconnects and gets a
  ``reset``. At most ``max_clients`` pages at once.

Bound to a loopback address, the server answers only requests whose ``Host`` is a
loopback name (a web page elsewhere cannot read it through DNS rebinding). It serves
read-only data and has no authentication: bind it to a public address only behind a
proxy that has.
"""

from __future__ import annotations

import json
import logging
import queue
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import zenoh

from hdmap.geo.area import BBox
from hdmap.geo.tiles import DEFAULT_ZOOM
from hdmap.ops.dashboard.geometry import (
    MAX_AREA_TILES,
    Sample,
    feature_collection,
    service_row,
    tile_features,
)
from hdmap.ops.dashboard.view import MapView
from hdmap.ops.status import collect
from hdmap.runtime.bus import BusConfig, open_session
from schemas import keys
from vehicle.mapclient import MapClient

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
CONTENT_TYPES = (
    (".html", "text/html; charset=utf-8"),
    (".js", "text/javascript; charset=utf-8"),
    (".css", "text/css; charset=utf-8"),
    (".json", "application/json"),
    (".txt", "text/plain; charset=utf-8"),
)
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1", "[::1]")
HISTORY_PATH = re.compile(r"^/api/history/([0-9]{1,20})$")


@dataclass(frozen=True)
class DashboardConfig:
    tiles: tuple[str, ...] = ()
    """The area's tiles (quadkeys at ``zoom``); none: follow the tiles that publish."""
    zoom: int = DEFAULT_ZOOM
    client_id: str = "dashboard"
    """The id its snapshot queries are made and limited under (``.../by/<id>``)."""
    refresh_s: float = 0.25
    stats_interval_s: float = 2.0
    stats_timeout_s: float = 2.0
    history_len: int = 50
    history_landmarks: int = 20_000
    max_clients: int = 16
    client_queue: int = 256
    keepalive_s: float = 15.0
    max_tiles: int = MAX_AREA_TILES
    """Most tiles followed in the no-area mode."""


def sse(event: str, data: Any) -> bytes:
    """One server-sent event (``data`` as one line of JSON)."""
    body = json.dumps(data, separators=(",", ":"), allow_nan=False, default=float)
    return f"event: {event}\ndata: {body}\n\n".encode()


class _Page:
    """One connected page: its queue of encoded events."""

    def __init__(self, size: int):
        self.queue: queue.Queue[bytes | None] = queue.Queue(size)
        self.dropped = False
        """Its queue was full: it is disconnected (and reconnects for a reset)."""


class Events:
    """Fan-out of server-sent events to the connected pages (bounded, thread-safe)."""

    def __init__(self, max_clients: int, queue_len: int):
        self.max_clients = max_clients
        self.queue_len = queue_len
        self._pages: set[_Page] = set()
        self._lock = threading.Lock()
        self._closed = False
        self.sent = 0
        self.dropped = 0

    def subscribe(self) -> _Page | None:
        """A new page's queue; None when ``max_clients`` are connected or closing."""
        with self._lock:
            if self._closed or len(self._pages) >= self.max_clients:
                return None
            page = _Page(self.queue_len)
            self._pages.add(page)
            return page

    def unsubscribe(self, page: _Page) -> None:
        with self._lock:
            self._pages.discard(page)

    def publish(self, event: str, data: Any) -> None:
        msg = sse(event, data)
        with self._lock:
            pages = list(self._pages)
            self.sent += 1
        for p in pages:
            try:
                p.queue.put_nowait(msg)
            except queue.Full:
                if not p.dropped:
                    p.dropped = True
                    with self._lock:
                        self.dropped += 1

    def close(self) -> None:
        with self._lock:
            self._closed = True
            pages = list(self._pages)
        for p in pages:
            try:
                p.queue.put_nowait(None)
            except queue.Full:
                p.dropped = True

    def __len__(self) -> int:
        with self._lock:
            return len(self._pages)


class Dashboard:
    """The map and stats side: a map client, the view, the events (no HTTP)."""

    def __init__(
        self,
        session: zenoh.Session,
        config: DashboardConfig,
        clock: Callable[[], float] = time.time,
    ):
        self.session = session
        self.config = config
        self.clock = clock
        self.view = MapView(config.history_len, config.history_landmarks)
        self.events = Events(config.max_clients, config.client_queue)
        self.client = MapClient(session, radius_m=0.0, zoom=config.zoom, client_id=config.client_id)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._discovered: queue.Queue[str] = queue.Queue(config.max_tiles)
        self._sub: zenoh.Subscriber | None = None
        self._threads: list[threading.Thread] = []
        self._versions: dict[str, int] = {}
        self._tiles_state: tuple[tuple[str, bool], ...] = ()
        self._samples: dict[tuple[str, str], Sample] = {}
        self._stats: dict[str, Any] = {"services": [], "updated_at": None, "error": None}
        self.refreshes = 0

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        for tile in self.config.tiles:
            self.client.follow(tile)
        if not self.config.tiles:
            self._sub = self.session.declare_subscriber(keys.map_delta(keys.ANY), self._on_delta)
        for name, target in (
            ("dashboard-map", self._map_loop),
            ("dashboard-stats", self._stats_loop),
        ):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def close(self) -> None:
        """Stop the threads, undeclare, close the map client and the pages' streams."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=10)
        if self._sub is not None:
            self._sub.undeclare()
        self.client.close()
        self.events.close()

    def _on_delta(self, sample: zenoh.Sample) -> None:
        """Zenoh callback (no-area mode): queue the tile of a delta seen (only queues)."""
        tile = keys.chunk(str(sample.key_expr), 3)
        if tile not in self._versions:
            try:
                self._discovered.put_nowait(tile)
            except queue.Full:
                pass

    # -- map ---------------------------------------------------------------------------------

    def _map_loop(self) -> None:
        while not self._stop.wait(self.config.refresh_s):
            try:
                self.refresh()
            except Exception:  # the page must keep its server: log, try again next time
                log.exception("dashboard: map refresh failed")

    def _follow_discovered(self) -> None:
        followed = self.client.versions()
        while True:
            try:
                tile = self._discovered.get_nowait()
            except queue.Empty:
                return
            if tile in followed:
                continue
            if len(followed) >= self.config.max_tiles:
                log.warning("dashboard: %d tiles followed, not following %s", len(followed), tile)
                continue
            self.client.follow(tile)
            followed[tile] = -1

    def refresh(self) -> bool:
        """Push what changed since the last refresh; whether anything had."""
        if self._sub is not None:
            self._follow_discovered()
        versions = self.client.versions()  # before the landmarks: a later change shows next time
        if versions == self._versions:
            return False
        self._versions = versions
        change = self.view.update(self.client.landmarks(), self.clock())
        self.refreshes += 1
        if change:
            self.events.publish(
                "delta", {**change.to_json(), "counts": self.view.counts(), "at": self.clock()}
            )
        state = tuple(sorted((t, v >= 0) for t, v in versions.items()))
        if state != self._tiles_state:
            self._tiles_state = state
            self.events.publish("tiles", self.tiles_json())
        return bool(change)

    def tiles_json(self) -> dict[str, Any]:
        versions = self.client.versions()
        around = BBox.of_tiles(versions)
        return {
            "tiles": feature_collection(tile_features(versions)),
            "bounds": None if around is None else list(around.as_tuple()),
        }

    # -- stats ------------------------------------------------------------------------------

    def _stats_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll_stats()
            except Exception:  # a bus hiccup must not end the panel
                log.exception("dashboard: stats poll failed")
            if self._stop.wait(self.config.stats_interval_s):
                return

    def poll_stats(self) -> dict[str, Any]:
        """Ask the services for their stats once; the panel's data (also pushed)."""
        error = None
        try:
            stats = collect(self.session, self.config.stats_timeout_s)
        except zenoh.ZError as exc:
            stats, error = [], str(exc)
        now = self.clock()
        rows = []
        samples: dict[tuple[str, str], Sample] = {}
        for s in stats:
            key = (s.service, s.instance)
            row, samples[key] = service_row(s, self._samples.get(key), now)
            rows.append(row)
        self._samples = samples
        c = self.client.stats
        data = {
            "services": rows,
            "updated_at": now,
            "error": error,
            "map_client": {
                "tiles": len(self._versions),
                "tiles_fetched": sum(v >= 0 for v in self._versions.values()),
                "snapshots": c.snapshots,
                "snapshots_refused": c.snapshots_refused,
                "deltas_applied": c.deltas_applied,
                "gaps": c.gaps,
                "resyncs": c.resyncs,
            },
            "landmarks": len(self.view),
            "counts": self.view.counts(),
            "pages": len(self.events),
        }
        with self._lock:
            self._stats = data
        self.events.publish("stats", data)
        return data

    def stats_json(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._stats)

    def reset_json(self) -> dict[str, Any]:
        """What a page gets on connecting: the whole map, the tiles, the latest stats."""
        return {
            "landmarks": self.view.collection(),
            "counts": self.view.counts(),
            **self.tiles_json(),
            "stats": self.stats_json(),
            "at": self.clock(),
        }


# -- HTTP ----------------------------------------------------------------------------------


class DashboardServer(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, address: tuple[str, int], dashboard: Dashboard):
        self.dashboard = dashboard
        self.static = {p.name: p for p in STATIC_DIR.iterdir() if p.is_file()}
        self.check_host = address[0] in LOOPBACK_NAMES
        super().__init__(address, Handler)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{f'[{host}]' if ':' in str(host) else host}:{port}/"


class Handler(BaseHTTPRequestHandler):
    server: DashboardServer
    server_version = "hdmap-dashboard"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s %s", self.address_string(), format % args)

    def do_GET(self) -> None:
        if not self._host_ok():
            self._send(403, b"forbidden host\n", "text/plain")
            return
        path = self.path.split("?", 1)[0]
        d = self.server.dashboard
        if path in ("/", "/index.html"):
            self._file("index.html")
        elif path.startswith("/static/"):
            self._file(path.removeprefix("/static/"))
        elif path == "/events":
            self._events()
        elif path == "/api/landmarks":
            self._json(d.view.collection())
        elif path == "/api/stats":
            self._json(d.stats_json())
        elif path == "/api/tiles":
            self._json(d.tiles_json())
        elif m := HISTORY_PATH.match(path):
            entries = d.view.history(m.group(1))
            if entries is None:
                self._json({"id": m.group(1), "error": "not seen"}, 404)
            else:
                self._json({"id": m.group(1), "entries": entries})
        else:
            self._send(404, b"not found\n", "text/plain")

    def _host_ok(self) -> bool:
        if not self.server.check_host:
            return True
        host = self.headers.get("Host", "")
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        return name in LOOPBACK_NAMES

    def _send(self, code: int, body: bytes, ctype: str, cache: str = "no-cache") -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", cache)
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, data: Any, code: int = 200) -> None:
        body = json.dumps(data, separators=(",", ":"), allow_nan=False, default=float).encode()
        self._send(code, body, "application/json")

    def _file(self, name: str) -> None:
        p = self.server.static.get(name)
        if p is None:
            self._send(404, b"not found\n", "text/plain")
            return
        ctype = next(
            (t for ext, t in CONTENT_TYPES if name.endswith(ext)), "application/octet-stream"
        )
        cache = "max-age=3600" if name.startswith("maplibre-gl") else "no-cache"
        self._send(200, p.read_bytes(), ctype, cache)

    def _events(self) -> None:
        d = self.server.dashboard
        page = d.events.subscribe()  # before the reset: nothing after it is missed
        if page is None:
            self._send(503, b"too many pages connected\n", "text/plain")
            return
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-cache")
            self.send_header("X-Accel-Buffering", "no")
            self.end_headers()
            self.wfile.write(b"retry: 2000\n\n" + sse("reset", d.reset_json()))
            self.wfile.flush()
            while not page.dropped:
                try:
                    msg = page.queue.get(timeout=d.config.keepalive_s)
                except queue.Empty:
                    msg = b": keepalive\n\n"
                if msg is None or page.dropped:
                    break
                self.wfile.write(msg)
                self.wfile.flush()
        except OSError:  # the page went away
            pass
        finally:
            d.events.unsubscribe(page)
            self.close_connection = True


# -- the whole -----------------------------------------------------------------------------


def serve(
    bus: BusConfig,
    host: str,
    port: int,
    config: DashboardConfig,
    stop: threading.Event,
    ready: Callable[[str], None] | None = None,
) -> None:
    """Run the dashboard until ``stop`` is set; ``ready(url)`` once it serves. Raises
    ``zenoh.ZError`` (no router reachable) and ``OSError`` (the port is taken)."""
    with open_session(bus) as session:
        dashboard = Dashboard(session, config)
        try:
            server = DashboardServer((host, port), dashboard)
        except OSError:
            dashboard.close()
            raise
        thread = threading.Thread(target=server.serve_forever, name="dashboard-http", daemon=True)
        try:
            dashboard.start()
            thread.start()
            if ready is not None:
                ready(server.url)
            stop.wait()
        finally:
            dashboard.close()  # ends the event streams first
            if thread.is_alive():
                server.shutdown()
            server.server_close()
            thread.join(timeout=10)
