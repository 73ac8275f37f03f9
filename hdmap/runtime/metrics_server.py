"""A service's Prometheus endpoint: ``GET /metrics`` from a daemon thread.

:class:`ServiceMetrics` holds a service's histograms (:mod:`hdmap.runtime.metrics`) and,
when its :class:`~hdmap.runtime.metrics.MetricsConfig` has a port, a
:class:`MetricsServer`: Python's ``ThreadingHTTPServer`` bound when the service is built
(a port that cannot be bound is a :class:`~hdmap.runtime.config.ConfigError`: ``hdmap
service`` exits with 78, which ``hdmap up`` does not restart), serving from a daemon thread
while the service runs, shut down and closed when it stops. Each scrape renders the
service's stats as they are at that moment (the stats a ``hdmap status`` query reads, so
both agree) plus the histograms. With no port nothing is bound and nothing is measured.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable, Sequence
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

from hdmap.runtime.config import ConfigError
from hdmap.runtime.metrics import (
    CONTENT_TYPE,
    ITEMS_BUCKETS,
    SECONDS_BUCKETS,
    Histogram,
    MetricsConfig,
    metric_name,
    render,
    stats_families,
)

log = logging.getLogger(__name__)


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_GET(self) -> None:
        if self.path.split("?", 1)[0] != "/metrics":
            self._send(404, b"not found: the metrics are at /metrics\n", "text/plain")
            return
        try:
            body = self.server.render().encode()
        except Exception:  # a failed scrape answers 500, the service goes on
            log.exception("metrics: rendering failed")
            self._send(500, b"rendering the metrics failed (see the service's log)\n", "text/plain")
            return
        self._send(200, body, CONTENT_TYPE)

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("metrics %s: " + format, self.address_string(), *args)


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, address: tuple[str, int], render: Callable[[], str]):
        self.render = render
        if ":" in address[0]:  # an IPv6 address ("::1", "::")
            self.address_family = socket.AF_INET6
        super().__init__(address, _Handler)


class MetricsServer:
    """``GET /metrics`` on ``host:port``: bound here, served by :meth:`start` from a daemon
    thread, stopped by :meth:`close`."""

    def __init__(self, config: MetricsConfig, render: Callable[[], str]):
        try:
            self._server = _Server((config.host, config.port), render)
        except OSError as exc:
            raise ConfigError(
                f"metrics.port: cannot serve on {config.host}:{config.port}: {exc}"
            ) from exc
        self._thread: threading.Thread | None = None

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._server.server_address[:2]
        return str(host), int(port)

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._server.serve_forever, kwargs={"poll_interval": 0.5},
                name="metrics", daemon=True,
            )  # fmt: skip
            self._thread.start()

    def close(self) -> None:
        if self._thread is not None:
            self._server.shutdown()  # returns once serve_forever has returned
            self._thread.join(5.0)
            self._thread = None
        self._server.server_close()


class ServiceMetrics:
    """A service's histograms and, if configured, its endpoint. ``service`` is a
    :class:`hdmap.runtime.service.Service` (its name, instance, region label, stats)."""

    def __init__(self, service: Any, config: MetricsConfig):
        self._service = service
        self.config = config
        self.enabled = config.enabled
        """Whether anything is measured and served (a port is configured)."""
        name = service.name
        self._extra: list[Histogram] = []
        self.batch_seconds = self.histogram(
            "batch_seconds", "seconds the worker took to handle one batch of its inbox"
        )
        self.batch_items = self.histogram(
            "batch_items", "items in one batch of the inbox", ITEMS_BUCKETS
        )
        self.inbox_wait_seconds = self.histogram(
            "inbox_wait_seconds",
            f"seconds an item waited in the {name} inbox before its batch began",
        )
        self.ingest_age_seconds = self.histogram(
            "ingest_age_seconds",
            "seconds from ingest's receipt of an upload to this service handling what came "
            "of it (wall clocks: across hosts as good as their synchronisation)",
        )
        self.server = MetricsServer(config, self.render) if config.enabled else None

    def histogram(
        self, name: str, help: str, buckets: Sequence[float] = SECONDS_BUCKETS
    ) -> Histogram:
        """A histogram ``hdmap_<service>_<name>`` in this service's scrape (for a service's
        own latencies: ``observe`` it where they are known; nothing is recorded unless
        :attr:`enabled`, so check it before work done only for the metrics)."""
        h = Histogram(metric_name("hdmap", self._service.name, name), help, buckets)
        self._extra.append(h)
        return h

    def batch_done(self, items: Sequence[Any], began: float, now: float | None = None) -> None:
        """The worker handled ``items`` (inbox items with their monotonic ``received``
        time) from ``began`` (monotonic) until ``now``."""
        if not self.enabled:
            return
        now = time.monotonic() if now is None else now
        self.batch_seconds.observe(max(now - began, 0.0))
        self.batch_items.observe(len(items))
        self.inbox_wait_seconds.observe_many(max(began - it.received, 0.0) for it in items)

    def ages(self, received_at: Any, now: float | None = None) -> None:
        """Items the service handles now whose uploads ingest received at ``received_at``
        (Unix seconds, an array or an iterable; the matcher: per obs entry, the solver:
        per link, the publisher: per landmark update)."""
        if not self.enabled:
            return
        now = time.time() if now is None else now
        t = np.asarray(received_at if isinstance(received_at, np.ndarray) else list(received_at))
        self.ingest_age_seconds.observe_many(np.maximum(now - t.astype(float), 0.0))

    def labels(self) -> dict[str, object]:
        s = self._service
        return {"service": s.name, "instance": s.instance, "region": s.region_label}

    def render(self) -> str:
        """The scrape: the stats counters, the rejected counts, the histograms."""
        s = self._service
        stats = s.stats()
        with s._stats_lock:  # the counters counted in transactions (the worker adds names)
            durable = set(s.counters) | {"rejected"}
        labels = self.labels()
        fams = stats_families(s.name, labels, stats.counters, stats.rejected, durable)
        fams += [h.family(labels) for h in self._extra]
        return render(fams)

    def start(self) -> None:
        if self.server is not None:
            self.server.start()
            host, port = self.server.address
            log.info("%s: metrics on http://%s:%d/metrics", self._service.name, host, port)

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
