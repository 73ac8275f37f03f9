"""``hdmap dashboard`` in a real headless Chromium, against a real stack.

A router and the four services are processes on 127.0.0.1 (random free ports, multicast
scouting off, SQLite under tmp_path; the ``stack`` fixture stops them, also on
failure). A small simulated fleet uploads half its passes; ``hdmap dashboard`` runs as a
subprocess over the town's tiles; Chromium (``chromedriver`` over W3C WebDriver,
:mod:`tests.support.webdriver`) loads the page. Checked in the page: MapLibre made its
map and drew the landmarks (the ``landmarks`` source holds exactly the publisher's
landmarks at their revisions, the point layer renders them, ellipses and facing arrows
are there, the services panel lists the four services); then the rest of the passes are
uploaded and the page follows the deltas to the publisher's new map; a real mouse click
on a landmark shows its history (its revision before and after). A screenshot PNG is
saved in tmp_path (its path printed; on failure too). Every wait is bounded.

Skipped, with the reason, where /usr/bin/chromium or /usr/bin/chromedriver is missing.
"""

from __future__ import annotations

import time
from itertools import islice
from pathlib import Path

import numpy as np
import pytest

from fleetsim.pipeline import FleetDriver
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import free_port
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from tests.support import wait_until
from tests.support.dashboard import dashboard_argv, http_json, publisher_map, town
from tests.support.processes import running
from tests.support.webdriver import Browser, WebDriverError, chrome, chromium_missing

MISSING = chromium_missing()

pytestmark = [
    pytest.mark.integration,
    pytest.mark.browser,
    pytest.mark.skipif(MISSING is not None, reason=f"browser test skipped: {MISSING}"),
]

PASSES = 32
FIRST = 16

PAGE_STATE = """
const h = window.hdmap;
if (!h || !h.map) return null;
const m = h.map;
const out = {ready: h.ready, loaded: m.loaded(), connected: h.connected, deltas: h.deltas,
             renders: h.renders, selected: h.selected, landmarks: {}, kinds: {}, rendered: []};
for (const [id, fs] of h.byId) {
  out.landmarks[id] = [fs[0].properties.revision, fs[0].properties.passes];
  for (const f of fs) out.kinds[f.properties.kind] = (out.kinds[f.properties.kind] || 0) + 1;
}
if (h.ready) {
  out.rendered = [...new Set(m.queryRenderedFeatures({layers: ['lm-point']})
                    .map(f => f.properties.id))];
}
out.services = [...document.querySelectorAll('#stats tbody tr td:first-child')]
  .map(td => td.textContent);
return out;
"""

SOURCE_DATA = """
const done = arguments[arguments.length - 1];
window.hdmap.map.getSource('landmarks').getData().then(
  d => done(d.features.filter(f => f.properties.kind === 'point')
             .map(f => [f.properties.id, f.properties.revision])),
  e => done('error: ' + e));
"""

FOCUS = """
const [id, done] = [arguments[0], arguments[arguments.length - 1]];
const h = window.hdmap, m = h.map, fs = h.byId.get(id);
m.jumpTo({center: fs[0].geometry.coordinates, zoom: 21});
const finish = () => {
  const p = m.project(fs[0].geometry.coordinates), r = m.getCanvas().getBoundingClientRect();
  done([p.x + r.left, p.y + r.top]);
};
m.once('idle', finish);
setTimeout(finish, 5000);
"""

FIT = """
const done = arguments[arguments.length - 1];
window.hdmap.fit();
window.hdmap.map.once('idle', () => done(true));
setTimeout(() => done(false), 5000);
"""


def page_landmarks(b: Browser) -> dict[str, tuple[int, int]]:
    state = b.execute(PAGE_STATE) or {}
    return {k: (v[0], v[1]) for k, v in state.get("landmarks", {}).items()}


def screenshot(b: Browser, path: Path) -> None:
    try:
        b.screenshot(path)
        print(f"dashboard screenshot: {path}")
    except (OSError, ValueError, WebDriverError) as exc:  # must not hide the failure
        print(f"dashboard screenshot failed: {exc}")


def test_dashboard_renders_the_live_map_in_chromium(stack, tmp_path):
    world, fl, tiles = town(4, PASSES)

    stack.start_all()
    with open_session(stack.bus) as s:
        driver = FleetDriver(world, fl, tmp_path / "vehicles")
        try:
            passes = fl.passes(PASSES)
            driver.run(s, islice(passes, FIRST))
            assert wait_quiet(s, timeout=120.0), totals(collect(s))
            before = publisher_map(s, tiles)
            assert len(before) >= 5, before

            port = free_port()
            url = f"http://127.0.0.1:{port}/"
            argv = dashboard_argv(stack.listen, port, "--tiles", ",".join(tiles))
            with running(argv, tmp_path / "dashboard.log") as dash:

                def serving() -> bool:
                    assert dash.poll() is None, (tmp_path / "dashboard.log").read_text()
                    try:
                        return len(http_json(url + "api/landmarks")["features"]) > 0
                    except OSError:
                        return False

                assert wait_until(serving, 30.0, 0.2)
                with chrome(tmp_path) as b:
                    try:
                        check_page(b, s, url, tiles, before, driver, passes, tmp_path)
                    finally:
                        screenshot(b, tmp_path / "dashboard.png")
            assert dash.returncode == 0, (tmp_path / "dashboard.log").read_text()[-3000:]
        finally:
            driver.close()


def check_page(b, s, url, tiles, before, driver, passes, tmp_path) -> None:
    b.navigate(url)

    # the page loads, MapLibre renders the publisher's landmarks
    def shown() -> bool:
        st = b.execute(PAGE_STATE)
        return bool(
            st
            and st["ready"]
            and st["loaded"]
            and st["connected"]
            and page_landmarks(b) == before
            and set(st["rendered"]) == set(before)
        )

    assert wait_until(shown, 60.0, 0.5), (b.execute(PAGE_STATE), before, b.log()[-10:])
    source = b.execute_async(SOURCE_DATA)
    assert isinstance(source, list), source
    assert {i: r for i, r in source} == {i: rv[0] for i, rv in before.items()}
    st = b.execute(PAGE_STATE)
    assert st["kinds"]["point"] == len(before)
    assert st["kinds"].get("ellipse", 0) == len(before)  # every landmark has a covariance
    assert st["kinds"].get("arrow", 0) >= 1  # facings of landmarks seen on 2+ passes
    assert wait_until(
        lambda: (
            {"ingest", "matcher", "solver", "publisher"} <= set(b.execute(PAGE_STATE)["services"])
        ),
        20.0,
        0.5,
    ), b.execute(PAGE_STATE)["services"]

    # more passes: the page follows the publisher's deltas
    deltas_before = b.execute(PAGE_STATE)["deltas"]
    driver.run(s, passes)
    assert wait_quiet(s, timeout=120.0), totals(collect(s))
    after = publisher_map(s, tiles)
    assert after != before
    assert wait_until(lambda: page_landmarks(b) == after, 30.0, 0.5), (
        page_landmarks(b),
        after,
    )
    assert b.execute(PAGE_STATE)["deltas"] > deltas_before
    changed = sorted(i for i in after if i in before and after[i] != before[i])
    assert changed or set(after) - set(before)

    # a click on a changed landmark shows its history: seen at both revisions
    lid = changed[0] if changed else sorted(set(after) - set(before))[0]
    x, y = b.execute_async(FOCUS, lid)
    b.click_at(x, y)
    assert wait_until(lambda: b.execute(PAGE_STATE)["selected"] == lid, 10.0, 0.2)

    def history_shown() -> bool:
        text = b.execute("return document.getElementById('landmark-body').innerText")
        return lid in text and "History as seen by this dashboard" in text

    assert wait_until(history_shown, 10.0, 0.2)
    hist = http_json(f"{url}api/history/{lid}")["entries"]
    revisions = [e["revision"] for e in hist]
    assert revisions == sorted(revisions) and revisions[-1] == after[lid][0]
    if lid in before:
        assert revisions[0] == before[lid][0] and len(revisions) >= 2
    assert np.isfinite([e["sigma_e_m"] for e in hist]).all()
    assert all(abs(e["seen_at"] - time.time()) < 600 for e in hist)
    rows = b.execute("return document.querySelectorAll('#landmark-body .history tbody tr').length")
    assert rows == len(hist)
    assert b.execute_async(FIT) is not None  # the whole town in the screenshot
