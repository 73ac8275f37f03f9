"""Event time: the same uploads sent paced, as they are driven, and back to back a day
late give the same map (issue 18, point 1).

Two stacks (a router and the four services as processes, random free port on 127.0.0.1,
multicast scouting off, SQLite under tmp_path), the same simulated passes captured a day
ago, uploaded in the same order: to one with a pause after each pass (every upload applied
alone, the wall clock moving on between them), to the other back to back (the services
catch up in large batches). The matcher's pending TTL, pass closing and sweep period and
the solver's pass closing are set to seconds of event time, so with passes 2 s apart in
capture time they all fire many times during the run; on the wall clock they would
also fire in the paced run (it lasts longer than the TTL) and not in the back-to-back
one, and the maps would differ.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.noise import FLEET
from fleetsim.pipeline import FleetDriver, model_for
from fleetsim.town_run import follow_town
from fleetsim.world import demo_town
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from schemas import Landmarks
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient

pytestmark = pytest.mark.integration

VEHICLES = 4
PASSES = 24
INTERVAL_S = 2.0
"""Capture time between consecutive passes (of the fleet; 8 s between one vehicle's)."""

EVENT_TIMERS = """\
[matcher]
pending_ttl_s = 5.0
close_passes_after_s = 12.0
sweep_every_s = 1.0

[matcher.trust]
probation_passes = 0

[solver]
close_passes_after_s = 12.0
sweep_every_s = 1.0
"""
"""Timers of seconds of event time (the defaults are an hour, two hours, a minute)."""


def fleet() -> Fleet:
    world = demo_town(3, n_signs=16, n_blocks=2)
    model = model_for(FLEET, load_vehicle_model())
    day_ago = time.time() - 86_400.0 - PASSES * INTERVAL_S
    cfg = FleetConfig(
        n_vehicles=VEHICLES,
        start_time=day_ago,
        pass_interval_s=INTERVAL_S,
        route_length_m=(300.0, 500.0),
    )
    return Fleet(world, model, FLEET, cfg, seed=3)


def run(tmp, fl: Fleet, pause_s: float) -> tuple[Landmarks, dict]:
    """Every pass uploaded in order, ``pause_s`` after each; the final map and counters."""
    with Stack(tmp) as stack:
        cfg = tmp / "event_timers.toml"
        cfg.write_text(EVENT_TIMERS)
        for name in ("matcher", "solver"):
            stack.extra_service_args[name] = ["--config", str(cfg)]
        stack.start_all()
        with open_session(stack.bus) as s:
            client = MapClient(s, radius_m=0.0)
            follow_town(client, fl.world)
            driver = FleetDriver(fl.world, fl, tmp / "vehicles")
            try:
                for p in fl.passes(PASSES):
                    driver.run(s, iter([p]))
                    time.sleep(pause_s)
                assert wait_quiet(s, timeout=120.0), totals(collect(s))
                time.sleep(1.0)  # the publisher's last coalescing interval
                assert client.wait_idle(10.0)
                return client.landmarks(), totals(collect(s))
            finally:
                client.close()
                driver.close()


def by_id(lm: Landmarks) -> dict[int, np.ndarray]:
    return {int(i): np.r_[lm.lat[k], lm.lon[k], lm.h[k], lm.cov[k]] for k, i in enumerate(lm.id)}


def test_paced_and_bulk_a_day_late_give_the_same_map(tmp_path):
    fl = fleet()
    paced, st_paced = run(tmp_path / "paced", fl, pause_s=0.6)
    bulk, st_bulk = run(tmp_path / "bulk", fl, pause_s=0.0)
    m_p, m_b = st_paced["matcher"], st_bulk["matcher"]
    # the timers fired, the same number of times: rays expired, passes closed
    assert m_p.get("expired", 0) > 0 and m_p.get("passes_closed", 0) > 0, m_p
    assert st_paced["solver"].get("passes_closed", 0) > 0
    for k in ("received", "linked", "expired", "passes_closed", "created"):
        assert m_p.get(k, 0) == m_b.get(k, 0), (k, m_p, m_b)
    # the paced run's matcher applied one upload at a time, the bulk one caught up
    assert m_b["entries_applied"] == m_p["entries_applied"]
    p, b = by_id(paced), by_id(bulk)
    assert len(p) >= 5
    assert p.keys() == b.keys()
    for i in p:
        np.testing.assert_allclose(b[i][:3], p[i][:3], rtol=0, atol=1e-9)
        np.testing.assert_allclose(b[i][3:], p[i][3:], rtol=1e-6, atol=1e-9)
