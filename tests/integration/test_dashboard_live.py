"""``hdmap dashboard`` over HTTP (no browser): the no-area mode, the event stream, the
API, and its refusals.

A router and the four services are processes on 127.0.0.1 (random free ports, multicast
scouting off, SQLite under tmp_path; the ``stack`` fixture stops them, also on
failure); the dashboard is a subprocess (stopped by SIGTERM at the end; it must exit 0).
Every wait is bounded.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import pytest

from fleetsim.pipeline import FleetDriver
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import free_port
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from tests.support import wait_until
from tests.support.dashboard import (
    dashboard_argv,
    http_json,
    publisher_map,
    served_landmarks,
    town,
)
from tests.support.processes import running

pytestmark = pytest.mark.integration


def first_event(url: str, max_lines: int = 50) -> tuple[str, dict]:
    """The first server-sent event of ``/events`` (name, data); bounded in lines and time."""
    with urllib.request.urlopen(url + "events", timeout=10.0) as r:
        assert r.headers["Content-Type"] == "text/event-stream"
        name = ""
        for _ in range(max_lines):
            line = r.readline().decode().rstrip("\n")
            if line.startswith("event: "):
                name = line.removeprefix("event: ")
            elif line.startswith("data: ") and name:
                return name, json.loads(line.removeprefix("data: "))
    raise AssertionError("no event")


def test_without_an_area_it_follows_the_tiles_that_publish(stack, tmp_path):
    world, fl, tiles = town(3, 8)
    stack.start_all()
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    log = tmp_path / "dashboard.log"
    with running(dashboard_argv(stack.listen, port), log) as dash:

        def up() -> bool:
            assert dash.poll() is None, log.read_text()
            try:
                return "services" in http_json(url + "api/stats")  # type: ignore[operator]
            except OSError:
                return False

        assert wait_until(up, 30.0, 0.2)
        assert served_landmarks(url) == {}  # nothing has published yet

        # the port is taken: a second dashboard says so and exits 2
        log2 = tmp_path / "dashboard2.log"
        with running(dashboard_argv(stack.listen, port), log2) as dup:
            assert wait_until(lambda: dup.poll() is not None, 30.0, 0.1)
        assert dup.returncode == 2 and "cannot listen" in log2.read_text()

        with open_session(stack.bus) as s:
            driver = FleetDriver(world, fl, tmp_path / "vehicles")
            try:
                driver.run(s, fl.passes(8))
                assert wait_quiet(s, timeout=120.0), totals(collect(s))
            finally:
                driver.close()
            published = publisher_map(s, tiles)
        assert len(published) >= 3
        assert wait_until(lambda: served_landmarks(url) == published, 30.0, 0.2), (
            served_landmarks(url),
            published,
        )

        # a page connecting gets the whole map first
        name, data = first_event(url)
        assert name == "reset"
        points = [f for f in data["landmarks"]["features"] if f["properties"]["kind"] == "point"]
        assert {f["properties"]["id"] for f in points} == set(published)
        assert sum(data["counts"].values()) == len(published)
        assert data["tiles"]["features"] and len(data["bounds"]) == 4

        # the API
        lid = sorted(published)[0]
        hist = http_json(f"{url}api/history/{lid}")["entries"]  # type: ignore[index]
        assert hist[-1]["revision"] == published[lid][0]
        with pytest.raises(urllib.error.HTTPError) as e:
            http_json(f"{url}api/history/12345")
        assert e.value.code == 404
        assert wait_until(
            lambda: (
                {r["service"] for r in http_json(url + "api/stats")["services"]}  # type: ignore[index]
                == {"ingest", "matcher", "solver", "publisher"}
            ),
            20.0,
            0.5,
        )
        assert len(http_json(url + "api/tiles")["tiles"]["features"]) >= 1  # type: ignore[index]
        with urllib.request.urlopen(url + "static/maplibre-gl.js", timeout=5.0) as r:
            assert r.headers["Content-Type"].startswith("text/javascript")
            assert len(r.read()) > 500_000
        for bad in ("static/../server.py", "static/nope.js", "api/history/abc"):
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(url + bad, timeout=5.0)
            assert e.value.code == 404, bad
        # bound to loopback: a request naming another host (DNS rebinding) is refused
        with pytest.raises(urllib.error.HTTPError) as e:
            http_json(url + "api/landmarks", headers={"Host": f"evil.example:{port}"})
        assert e.value.code == 403
    assert dash.returncode == 0, log.read_text()[-3000:]
