"""A sign on a tile border becomes one landmark, not one per tile.

One sign beside a straight road, placed 0.3 m south of the border between two zoom-16
tiles (its corner, so four tiles meet nearby); the rays of the passes are routed to either
tile depending on their range estimates and noise. Real router and services.
"""

from __future__ import annotations

import numpy as np
import pytest

from fleetsim.fleet import Fleet
from fleetsim.noise import FLEET
from fleetsim.pipeline import FleetDriver, fleet_config_ending_now, model_for
from fleetsim.town_run import follow_town
from fleetsim.world import HELSINKI, straight_road
from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.tiles import quadkey_of, quadkeys_of, tile_bounds
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient

pytestmark = pytest.mark.integration


def border_road():
    """straight_road() moved so that its sign stands 0.3 m south and 0.3 m west of a
    tile corner."""
    qk = quadkey_of(HELSINKI[0], HELSINKI[1])
    b = tile_bounds(qk)
    corner = EnuFrame(b.north, b.east, HELSINKI[2])
    sign = straight_road().signs.position[0]
    anchor = corner.to_geodetic(np.array([[-sign[0] - 0.3, -sign[1] - 0.3, 0.0]]))
    world = straight_road(anchor=(float(anchor[0][0]), float(anchor[1][0]), HELSINKI[2]))
    return world


def test_sign_on_a_tile_corner_is_one_landmark(stack, tmp_path):
    world = border_road()
    lat, lon, _ = world.signs_geodetic()
    d = 0.6 / 111_000  # ~0.6 m in degrees: the tiles on either side differ
    around = quadkeys_of(
        lat[0] + np.array([-d, d, -d, d]), lon[0] + np.array([-2 * d, -2 * d, 2 * d, 2 * d])
    )
    assert len(set(around.tolist())) == 4, around
    model = model_for(FLEET, load_vehicle_model())
    fleet = Fleet(
        world, model, FLEET, fleet_config_ending_now(3, 30, route_length_m=(170.0, 180.0)), 3
    )
    stack.start_all()
    with open_session(stack.bus) as s:
        client = MapClient(s, radius_m=0.0)
        follow_town(client, world)
        driver = FleetDriver(world, fleet, tmp_path / "v")
        try:
            driver.run(s, fleet.passes(30))
            assert wait_quiet(s, timeout=120.0)
            assert client.wait_idle(20.0)
            lm = client.landmarks()
            stats = totals(collect(s))
        finally:
            client.close()
            driver.close()
    est = world.frame.from_geodetic(lm.lat, lm.lon, lm.h).reshape(-1, 3)
    near = np.linalg.norm(est[:, :2] - world.signs.position[0, :2], axis=1) < 10.0
    same = lm.sign_class == world.signs.sign_class[0]
    print(
        f"{int((near & same).sum())} landmark(s) of the sign's class within 10 m; tiles "
        f"of the observations: {stats['ingest'].get('log_entries')} log entries"
    )
    assert int((near & same).sum()) == 1
    # the rays really went to several tiles: ingest writes one log entry per (upload,
    # tile), each pass is one upload (~20 observations), so > 30 entries means spread
    assert stats["ingest"]["uploads"] == 30
    assert stats["ingest"]["log_entries"] >= 45
