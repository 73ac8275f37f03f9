"""A real ingest process with ``--metrics-port``, scraped over HTTP (urllib) like Prometheus.

Router and service are their own processes on 127.0.0.1 (free ports, SQLite under
tmp_path), stopped by the ``stack`` fixture also on failure; every wait is bounded."""

from __future__ import annotations

import re
import socket
import time
import urllib.request

import pytest

from fleetsim.synthetic import make_observations
from hdmap.ops.stack import free_port
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from hdmap.runtime.config import EXIT_CONFIG
from hdmap.runtime.metrics import CONTENT_TYPE
from schemas import ObservationBatch, UploadAck, keys
from tests.support import wait_until

pytestmark = pytest.mark.integration


def scrape(port: int) -> tuple[str, str]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as r:
        return r.headers["Content-Type"], r.read().decode()


def sample(text: str, name: str, **labels: str) -> float | None:
    """The value of the first sample of ``name`` whose labels include ``labels``."""
    for line in text.splitlines():
        m = re.match(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{.*\})? (\S+)$", line)
        if not m or m[1] != name:
            continue
        got = dict(re.findall(r'([a-zA-Z_]+)="((?:[^"\\]|\\.)*)"', m[2] or ""))
        if all(got.get(k) == v for k, v in labels.items()):
            return float(m[3])
    return None


def upload(session, vehicle: str, payload: bytes) -> UploadAck:
    replies = query(session, keys.upload(vehicle), payload, timeout=10.0)
    assert len(replies) == 1 and replies[0][1] is not None
    return UploadAck.from_bytes(replies[0][1])


def test_ingest_serves_its_counters_rejections_and_batch_histograms(stack) -> None:
    port = free_port()
    stack.start_router()
    stack.start_service("ingest", (), "--metrics-port", str(port))
    stack.wait_ready(["ingest-all"], 60)
    with open_session(stack.bus) as s:
        good = ObservationBatch("veh-1", 1, 1, time.time(), make_observations(20)).to_bytes()
        assert upload(s, "veh-1", good).error is None
        assert upload(s, "veh-1", b"not msgpack").error is not None
        stats = [x for x in collect(s) if x.service == "ingest"]
    assert len(stats) == 1
    instance = stats[0].instance

    ctype, text = scrape(port)
    assert ctype == CONTENT_TYPE
    lab = {"service": "ingest", "instance": instance, "region": "all"}
    assert "# TYPE hdmap_ingest_accepted_total counter" in text
    assert sample(text, "hdmap_ingest_accepted_total", **lab) == 20
    assert sample(text, "hdmap_ingest_accepted_total") == stats[0].counters["accepted"]
    assert "# TYPE hdmap_ingest_backlog gauge" in text
    assert sample(text, "hdmap_ingest_uptime_s", **lab) > 0
    reasons = {r: n for r, n in stats[0].rejected.items()}
    assert reasons and all(r.startswith("batch.") for r in reasons)
    for reason, n in reasons.items():
        assert sample(text, "hdmap_ingest_rejected_total", reason=reason, **lab) == n
    # every upload was one batch of the worker: two observations of the batch time
    assert "# TYPE hdmap_ingest_batch_seconds histogram" in text
    assert sample(text, "hdmap_ingest_batch_seconds_count", **lab) >= 2
    assert sample(text, "hdmap_ingest_batch_seconds_bucket", le="+Inf", **lab) == sample(
        text, "hdmap_ingest_batch_seconds_count", **lab
    )
    assert sample(text, "hdmap_ingest_inbox_wait_seconds_count", **lab) >= 2

    assert stack.stop("ingest-all") == 0  # SIGTERM: the endpoint goes with the service
    with pytest.raises(OSError), socket.create_connection(("127.0.0.1", port), timeout=2):
        pass


def test_a_metrics_port_in_use_stops_the_service_as_a_refused_configuration(stack) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        stack.start_router()
        p = stack.start_service("publisher", (), "--metrics-port", str(port))
        assert wait_until(lambda: not p.alive, 60.0)
        assert p.returncode == EXIT_CONFIG
        assert "metrics.port: cannot serve on" in p.log_path.read_text()


def test_the_matcher_measures_how_long_after_ingest_it_handles_an_upload(stack) -> None:
    port = free_port()
    stack.start_router()
    stack.start_service("ingest")
    stack.start_service("matcher", (), "--metrics-port", str(port))
    stack.wait_ready(["ingest-all", "matcher-all"], 60)
    with open_session(stack.bus) as s:
        t0 = time.time()
        good = ObservationBatch("veh-1", 1, 1, t0, make_observations(20, t=t0 - 5)).to_bytes()
        assert upload(s, "veh-1", good).error is None

        def applied() -> bool:
            m = [x for x in collect(s) if x.service == "matcher"]
            return bool(m) and m[0].counters.get("entries_applied", 0) >= 1

        assert wait_until(applied, 60.0)
    elapsed = time.time() - t0
    _ctype, text = scrape(port)
    n = sample(text, "hdmap_matcher_ingest_age_seconds_count")
    total = sample(text, "hdmap_matcher_ingest_age_seconds_sum")
    assert n is not None and n >= 1  # one obs entry per tile the upload touched
    assert total is not None and 0.0 <= total / n <= elapsed
