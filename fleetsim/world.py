"""The simulated world: a geodetic anchor, roads, buildings and traffic signs.

Everything is in the local ENU frame of the anchor (metres; x East, y North,
z Up, ground at z = 0). Roads form a graph: ``nodes`` (K, 2) and directed
``edges`` (E, 2) that vehicles may drive; a route is a walk on that graph.
Signs stand beside the road, facing oncoming traffic: ``facing`` is the unit
horizontal normal of the panel, pointing toward the vehicles that should see it.

>>> w = straight_road(5.0, 2.4)
>>> len(w.signs), w.signs.position[0].tolist()
(1, [6.75, 0.0, 2.4])
>>> round(float(w.signs.facing_azimuth_deg[0]), 6)  # faces South, toward northbound cars
180.0
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.signs import CATALOG, SignCatalog
from hdmap.geo.tiles import DEFAULT_ZOOM, tile_xy

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

HELSINKI = (60.1699, 24.9384, 20.0)
"""Anchor of the demo town: lat, lon (deg), ellipsoidal height (m)."""


@dataclass(frozen=True)
class Signs:
    """Traffic signs, struct of arrays (one row per sign)."""

    id: IntArray
    sign_class: IntArray
    position: Array
    """(N, 3) panel centre, ENU m; z is the mounting height above the ground."""
    facing: Array
    """(N, 3) unit horizontal normal of the panel, toward the traffic that sees it."""
    panel_height_m: Array

    def __len__(self) -> int:
        return int(self.id.size)

    @property
    def facing_azimuth_deg(self) -> Array:
        """Direction the panel faces, degrees clockwise from North, in [0, 360)."""
        return np.degrees(np.arctan2(self.facing[:, 0], self.facing[:, 1])) % 360.0

    def index_of(self, ids: NDArray) -> IntArray:
        """Rows of the given sign ids; -1 for unknown ids (e.g. false positives)."""
        ids = np.asarray(ids, np.int64)
        if not len(self):
            return np.full(ids.shape, -1, np.int64)
        order = np.argsort(self.id, kind="stable")
        sorted_ids = self.id[order]
        pos = np.clip(np.searchsorted(sorted_ids, ids), 0, len(self) - 1)
        return np.where(sorted_ids[pos] == ids, order[pos], -1)

    def with_real_sizes(self, rel_sigma: ArrayLike, seed: int) -> Signs:
        """These signs with panels as real ones are: each its class's nominal height times
        ``exp(N(0, rel_sigma))`` (per sign; ``rel_sigma`` per sign or one for all), drawn
        from ``seed`` and the sign's id, so a sign keeps its size whatever else is drawn.
        The vehicle still assumes the nominal heights (its box ranges err by the same factor
        for every look at that panel)."""
        rel = np.broadcast_to(np.asarray(rel_sigma, float), self.id.shape)
        z = np.array(
            [np.random.default_rng([seed, int(i), 0x51E5]).standard_normal() for i in self.id]
        ).reshape(self.id.shape)
        return replace(self, panel_height_m=self.panel_height_m * np.exp(rel * z))

    def take(self, rows: NDArray) -> Signs:
        r = np.asarray(rows)
        return Signs(
            self.id[r], self.sign_class[r], self.position[r], self.facing[r], self.panel_height_m[r]
        )

    @staticmethod
    def build(
        sign_class: NDArray,
        position: NDArray,
        facing_az_deg: NDArray,
        catalog: SignCatalog = CATALOG,
        ids: NDArray | None = None,
    ) -> Signs:
        cls = np.asarray(sign_class, np.int64)
        if not catalog.known(cls).all():
            raise ValueError(f"unknown sign classes: {sorted(set(cls[~catalog.known(cls)]))}")
        az = np.radians(np.asarray(facing_az_deg, float))
        facing = np.stack([np.sin(az), np.cos(az), np.zeros_like(az)], axis=-1)
        n = cls.size
        return Signs(
            id=np.arange(n, dtype=np.int64) if ids is None else np.asarray(ids, np.int64),
            sign_class=cls,
            position=np.asarray(position, float).reshape(n, 3),
            facing=facing.reshape(n, 3),
            panel_height_m=catalog.heights(cls),
        )


@dataclass(frozen=True)
class World:
    """Anchor, road graph, buildings (occluders) and signs."""

    frame: EnuFrame
    nodes: Array
    """(K, 2) road-graph nodes (intersections, road ends), ENU m."""
    edges: IntArray
    """(E, 2) directed edges (from, to) that vehicles may drive."""
    signs: Signs
    lane_offset_m: float = 1.75
    """Vehicles drive this far right of the road centreline."""
    buildings: Array = field(default_factory=lambda: np.zeros((0, 4)))
    """(B, 4) axis-aligned footprints (x_min, y_min, x_max, y_max) that block sight."""

    @property
    def lat0(self) -> float:
        return self.frame.lat0

    @property
    def lon0(self) -> float:
        return self.frame.lon0

    @property
    def h0(self) -> float:
        return self.frame.h0

    def signs_geodetic(self) -> tuple[Array, Array, Array]:
        """(lat deg, lon deg, h m) of every sign's panel centre."""
        lat, lon, h = self.frame.to_geodetic(self.signs.position)
        return np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(h)

    def roads(self) -> list[Array]:
        """Road centrelines as 2-point segments (one per undirected edge)."""
        e = np.sort(self.edges, axis=1)
        e = np.unique(e, axis=0)
        return [self.nodes[[a, b]] for a, b in e]

    def with_signs(self, signs: Signs) -> World:
        """The same town with other signs (moved, removed or added signs)."""
        return replace(self, signs=signs)


def tile_border_distance(world: World, xy: NDArray, zoom: int = DEFAULT_ZOOM) -> Array:
    """Distance (m) from ENU points to the nearest border of their zoom-``zoom`` tile."""
    p = np.asarray(xy, float).reshape(-1, 2)
    pts = np.column_stack([p, np.zeros(len(p))])
    lat, lon, _ = world.frame.to_geodetic(pts)
    lat, lon = np.atleast_1d(lat), np.atleast_1d(lon)
    tx, ty = tile_xy(lat, lon, zoom)
    n = float(1 << zoom)
    west = tx / n * 360.0 - 180.0
    east = (tx + 1) / n * 360.0 - 180.0
    north = np.degrees(np.arctan(np.sinh(np.pi * (1.0 - 2.0 * ty / n))))
    south = np.degrees(np.arctan(np.sinh(np.pi * (1.0 - 2.0 * (ty + 1) / n))))
    m_per_deg_lat = 111_320.0
    m_per_deg_lon = m_per_deg_lat * np.cos(np.radians(lat))
    return np.min(
        np.stack(
            [
                (lon - west) * m_per_deg_lon,
                (east - lon) * m_per_deg_lon,
                (lat - south) * m_per_deg_lat,
                (north - lat) * m_per_deg_lat,
            ]
        ),
        axis=0,
    )


def _tile_border_lines(world: World, extent: float, zoom: int) -> tuple[Array, Array]:
    """ENU x of the constant-longitude borders and y of the constant-latitude ones."""
    corners = np.array([[-extent, -extent, 0.0], [extent, extent, 0.0]])
    lat, lon, _ = world.frame.to_geodetic(corners)
    (x0, x1), (y1, y0) = tile_xy(lat, lon, zoom)
    n = float(1 << zoom)
    xs, ys = [], []
    for tx in range(int(x0) + 1, int(x1) + 1):
        lon_b = tx / n * 360.0 - 180.0
        xs.append(world.frame.from_geodetic(world.lat0, lon_b, world.h0)[0])
    for ty in range(int(y0) + 1, int(y1) + 1):
        lat_b = float(np.degrees(np.arctan(np.sinh(np.pi * (1.0 - 2.0 * ty / n)))))
        ys.append(world.frame.from_geodetic(lat_b, world.lon0, world.h0)[1])
    return np.array(xs, float), np.array(ys, float)


def straight_road(
    lateral_offset_m: float = 5.0,
    sign_height_m: float = 2.4,
    *,
    length_before_m: float = 150.0,
    length_after_m: float = 30.0,
    sign_class: str = "speed_limit_50",
    lane_offset_m: float = 1.75,
    anchor: tuple[float, float, float] = HELSINKI,
) -> World:
    """One northbound road (x = 0) with one sign at y = 0 for the paper's simulation.

    Vehicles drive the lane ``lane_offset_m`` east of the centreline, northbound
    only (the sign faces South, toward them). The sign stands ``lateral_offset_m``
    right of the lane centre, its panel centre ``sign_height_m`` above the ground.
    """
    frame = EnuFrame(*anchor)
    nodes = np.array([[0.0, -length_before_m], [0.0, length_after_m]])
    signs = Signs.build(
        [CATALOG.code(sign_class)],
        [[lane_offset_m + lateral_offset_m, 0.0, sign_height_m]],
        [180.0],
    )
    return World(frame, nodes, np.array([[0, 1]], np.int64), signs, lane_offset_m)


# --- the demo town -----------------------------------------------------------------

_DEMO_CLASSES = (
    "stop",
    "give_way",
    "no_entry",
    "speed_limit_30",
    "speed_limit_40",
    "no_parking",
    "no_stopping",
    "pedestrian_crossing",
    "priority_road",
    "one_way",
    "parking",
    "children",
    "bus_stop",
)


def _grid(n_blocks: int, block_m: float) -> tuple[Array, IntArray]:
    k = n_blocks + 1
    off = n_blocks * block_m / 2.0
    ij = np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 2)
    nodes = ij * block_m - off
    idx = ij[:, 0] * k + ij[:, 1]
    edges = []
    for (i, j), a in zip(ij, idx, strict=True):
        if i + 1 < k:
            edges.append((a, (i + 1) * k + j))
        if j + 1 < k:
            edges.append((a, i * k + j + 1))
    e = np.array(edges, np.int64)
    return nodes.astype(float), np.concatenate([e, e[:, ::-1]])


def roadside(
    nodes: Array, edge: NDArray, frac: Array, lateral: Array, lane: float
) -> tuple[Array, Array]:
    """Points beside directed edges (right of travel), and the facing azimuth (deg)."""
    a, b = nodes[edge[:, 0]], nodes[edge[:, 1]]
    t = b - a
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    right = np.column_stack([t[:, 1], -t[:, 0]])
    xy = a + (b - a) * frac[:, None] + right * (lane + lateral)[:, None]
    facing = -t
    return xy, np.degrees(np.arctan2(facing[:, 0], facing[:, 1])) % 360.0


def demo_town(
    seed: int = 0,
    *,
    n_signs: int = 40,
    n_blocks: int = 4,
    block_m: float = 100.0,
    n_pairs: int = 4,
    n_border: int = 4,
    n_corner_pairs: int = 2,
    anchor: tuple[float, float, float] = HELSINKI,
    lane_offset_m: float = 1.75,
) -> World:
    """A grid of two-way streets near Helsinki with ``n_signs`` roadside signs.

    ``n_blocks`` x ``n_blocks`` blocks of ``block_m`` metres, buildings inset 10 m
    from the street centrelines. Signs stand 2.5-4 m right of the lane centre,
    panel centre 2.0-2.8 m high, facing oncoming traffic (+-8 deg). Included:
    ``n_pairs`` same-class pairs 3-10 m apart along the same kerb, ``n_border``
    signs within 15 m of a zoom-16 tile border (where streets cross one) and
    ``n_corner_pairs`` same-class pairs at junctions facing the two crossing streets
    (:func:`corner_pairs`, 8.5-10 m apart; drawn with their own generator; fewer when
    ``n_signs`` leaves no room).
    """
    rng = np.random.default_rng(seed)
    nodes, edges = _grid(n_blocks, block_m)
    frame = EnuFrame(*anchor)
    extent = n_blocks * block_m / 2.0
    inset = 10.0
    lo = np.arange(n_blocks) * block_m - extent + inset
    bx, by = np.meshgrid(lo, lo, indexing="ij")
    buildings = np.column_stack(
        [bx.ravel(), by.ravel(), bx.ravel() + block_m - 2 * inset, by.ravel() + block_m - 2 * inset]
    )
    codes = np.array([CATALOG.code(c) for c in _DEMO_CLASSES], np.int64)
    proto = World(frame, nodes, edges, Signs.build([], np.zeros((0, 3)), []), lane_offset_m)

    xy_l: list[Array] = []
    az_l: list[Array] = []
    cls_l: list[Array] = []

    # Signs within 15 m of a tile border: on streets crossing a border line.
    xs_b, ys_b = _tile_border_lines(proto, extent, DEFAULT_ZOOM)
    cands = []
    margin = 12.0
    for xb in xs_b:  # constant-longitude border: crossed by east-west streets
        if -extent + margin < xb < extent - margin:
            for y in np.unique(nodes[:, 1]):
                cands.append((xb, y, 0))
    for yb in ys_b:  # constant-latitude border: crossed by north-south streets
        if -extent + margin < yb < extent - margin:
            for x in np.unique(nodes[:, 0]):
                cands.append((x, yb, 1))
    if cands and n_border > 0:
        pick = rng.choice(len(cands), size=min(n_border, len(cands)), replace=False)
        for k in pick:
            x, y, axis = cands[k]
            d_along = rng.uniform(-8.0, 8.0)
            direction = rng.choice([-1.0, 1.0])
            t = np.array([direction, 0.0]) if axis == 0 else np.array([0.0, direction])
            right = np.array([t[1], -t[0]])
            lateral = lane_offset_m + rng.uniform(2.5, 4.0)
            xy_l.append((np.array([x, y]) + t * d_along + right * lateral)[None])
            az_l.append(np.array([np.degrees(np.arctan2(-t[0], -t[1])) % 360.0]))
            cls_l.append(rng.choice(codes, 1))

    # Same-class pairs along the same kerb, 3-10 m apart.
    n_rest = max(n_signs - len(xy_l) - 2 * n_pairs, 0)
    e_pair = edges[rng.choice(len(edges), n_pairs, replace=False)]
    frac = rng.uniform(0.2, 0.75, n_pairs)
    gap = rng.uniform(3.0, 10.0, n_pairs) / block_m
    lat_p = rng.uniform(2.5, 4.0, n_pairs)
    cls_p = rng.choice(codes, n_pairs)
    for f in (frac, frac + gap):
        xy, az = roadside(nodes, e_pair, f, lat_p, lane_offset_m)
        xy_l.append(xy)
        az_l.append(az)
        cls_l.append(cls_p)

    # Same-class pairs at junctions, one facing each of two crossing streets.
    placed = np.concatenate(xy_l) if xy_l else np.zeros((0, 2))
    lat_c = (lane_offset_m + 2.5, lane_offset_m + 3.0)  # 2.5-3 m right of the lane centre
    corners = corner_pairs(
        nodes,
        edges,
        min(n_corner_pairs, n_rest // 2),  # within n_signs
        np.random.default_rng([seed, 7]),
        codes,
        lane_offset_m=lane_offset_m,
        lateral_m=(2.5, 3.0),
        setback_m=lat_c,
        keep_clear=placed,
    )
    if len(corners.xy):
        xy_l.append(corners.xy)
        az_l.append(corners.facing_az_deg)
        cls_l.append(corners.sign_class)
        placed = np.vstack([placed, corners.xy])
    n_rest = max(n_rest - len(corners.xy), 0)

    # The rest: anywhere along the streets, kept >= 12 m from the designed signs
    # and from each other (so the only close same-class signs are the pairs).
    rest_xy, rest_az = [], []
    while len(rest_xy) < n_rest:
        e = edges[rng.integers(len(edges))][None]
        xy, az = roadside(
            nodes, e, rng.uniform(0.12, 0.88, 1), rng.uniform(2.5, 4.0, 1), lane_offset_m
        )
        if placed.size and np.min(np.linalg.norm(placed - xy, axis=1)) < 12.0:
            continue
        placed = np.vstack([placed, xy])
        rest_xy.append(xy)
        rest_az.append(az)
    if rest_xy:
        xy_l.append(np.concatenate(rest_xy))
        az_l.append(np.concatenate(rest_az))
        # Every class at least once, then random ones.
        base = np.resize(codes, n_rest)
        cls_l.append(np.where(np.arange(n_rest) < codes.size, base, rng.choice(codes, n_rest)))

    xy_all = np.concatenate(xy_l)
    n = len(xy_all)
    az_all = np.concatenate(az_l) + rng.uniform(-8.0, 8.0, n)
    z = rng.uniform(2.0, 2.8, n)
    signs = Signs.build(np.concatenate(cls_l), np.column_stack([xy_all, z]), az_all)
    return World(frame, nodes, edges, signs, lane_offset_m, buildings)


# --- same-class pairs at intersections, facing different streets -----------------------


@dataclass(frozen=True)
class CornerPairs:
    """Same-class sign pairs at intersections, one for each of two crossing approaches.

    Rows ``2k`` and ``2k + 1`` are pair ``k``: each stands ``setback`` before the junction
    on the right of its approach (``lateral`` from the centreline) and faces that approach's
    traffic, so the two normals are the angle between the streets apart (60-120 deg) and
    the signs 5-10 m apart: one car stream sees one of them (the other is beyond the
    70-degree visibility cone of the panel), and their rays cross near both.
    """

    xy: Array
    """(2k, 2) positions, ENU m."""
    facing_az_deg: Array
    """(2k,) facing azimuths, degrees clockwise from North."""
    sign_class: IntArray
    """(2k,) class codes (one per pair, twice)."""
    node: IntArray
    """(k,) the junction (row of ``World.nodes``) of each pair."""


def segment_distance(p: Array, a: Array, b: Array) -> Array:
    """(n,) distance of each point to the nearest of the segments ``a[i] -> b[i]``."""
    t = b - a
    tt = np.maximum(np.sum(t * t, axis=1), 1e-12)
    u = np.clip(np.sum((p[:, None] - a) * t, axis=-1) / tt, 0.0, 1.0)
    f = a + u[..., None] * t
    return np.sqrt(np.min(np.sum((p[:, None] - f) ** 2, axis=-1), axis=1))


def corner_pairs(
    nodes: Array,
    edges: IntArray,
    n_pairs: int,
    rng: np.random.Generator,
    codes: NDArray,
    *,
    lane_offset_m: float = 1.75,
    lateral_m: tuple[float, float] = (2.5, 3.0),
    setback_m: tuple[float, float] = (3.6, 5.0),
    gap_m: tuple[float, float] = (5.0, 10.0),
    min_leg_m: float = 25.0,
    kerb_m: float = 3.5,
    angle_deg: tuple[float, float] = (60.0, 120.0),
    keep_clear: NDArray | None = None,
    keep_clear_cls: NDArray | None = None,
    clear_m: float = 12.0,
    class_clear_m: float = 20.0,
) -> CornerPairs:
    """Up to ``n_pairs`` :class:`CornerPairs` on the road graph (``nodes``, directed
    ``edges``), at distinct junctions: two approaches (edges into the junction at least
    ``min_leg_m`` long) crossing at ``angle_deg``; each sign ``setback_m`` before the
    junction, ``lane_offset_m + lateral_m`` right of the centreline, at least ``kerb_m``
    from every road, the two ``gap_m`` apart, both ``clear_m`` from the points
    ``keep_clear`` (other signs) and from earlier pairs, of a class (of ``codes``) that no
    sign of ``keep_clear`` (classes ``keep_clear_cls``; None: any) has within
    ``class_clear_m``. Fewer when the graph has fewer such junctions (drawn with ``rng``:
    deterministic per seed)."""
    a_all, b_all = nodes[edges[:, 0]], nodes[edges[:, 1]]
    leg = np.linalg.norm(b_all - a_all, axis=1)
    t_all = (b_all - a_all) / np.maximum(leg, 1e-9)[:, None]
    placed = np.zeros((0, 2)) if keep_clear is None else np.asarray(keep_clear, float)
    placed_cls = (
        np.full(len(placed), -1, np.int64)
        if keep_clear_cls is None
        else np.asarray(keep_clear_cls, np.int64)
    )
    xy_l: list[Array] = []
    az_l: list[float] = []
    cls_l: list[int] = []
    node_l: list[int] = []
    cos_lo, cos_hi = np.cos(np.radians(angle_deg[1])), np.cos(np.radians(angle_deg[0]))
    for v in rng.permutation(len(nodes)).tolist():
        if len(node_l) >= n_pairs:
            break
        into = np.flatnonzero((edges[:, 1] == v) & (leg >= min_leg_m))
        pairs = [
            (i, j)
            for i in into.tolist()
            for j in into.tolist()
            if i < j and cos_lo <= float(t_all[i] @ t_all[j]) <= cos_hi
        ]
        if not pairs:
            continue
        i, j = pairs[int(rng.integers(len(pairs)))]
        pts, azs = [], []
        for e in (i, j):
            t = t_all[e]
            right = np.array([t[1], -t[0]])
            back = rng.uniform(*setback_m)
            lateral = lane_offset_m + rng.uniform(*lateral_m)
            pts.append(nodes[v] - t * back + right * lateral)
            azs.append(float(np.degrees(np.arctan2(-t[0], -t[1])) % 360.0))
        p = np.array(pts)
        gap = float(np.linalg.norm(p[0] - p[1]))
        if not gap_m[0] <= gap <= gap_m[1]:
            continue
        if (segment_distance(p, a_all, b_all) < kerb_m).any():
            continue
        dist = np.linalg.norm(placed[None] - p[:, None], axis=-1).min(axis=0)
        if dist.size and dist.min() < clear_m:
            continue
        near = placed_cls[dist < class_clear_m]
        free = [] if (near < 0).any() else [int(c) for c in np.asarray(codes) if c not in near]
        if not free:
            continue
        c = free[int(rng.integers(len(free)))]
        placed = np.vstack([placed, p])
        placed_cls = np.r_[placed_cls, c, c]
        xy_l.append(p)
        az_l += azs
        cls_l += [c, c]
        node_l.append(v)
    return CornerPairs(
        np.concatenate(xy_l) if xy_l else np.zeros((0, 2)),
        np.array(az_l, float),
        np.array(cls_l, np.int64),
        np.array(node_l, np.int64),
    )


def corner_pair_rows(
    world: World, max_gap_m: float = 10.0, min_angle_deg: float = 45.0
) -> IntArray:
    """(K, 2) sign rows i < j of one class at most ``max_gap_m`` apart whose facings differ
    by at least ``min_angle_deg``: signs at a corner facing different streets."""
    s = world.signs
    dd = np.linalg.norm(s.position[:, None, :2] - s.position[None, :, :2], axis=-1)
    same = s.sign_class[:, None] == s.sign_class[None, :]
    cos = s.facing[:, :2] @ s.facing[:, :2].T
    turned = cos <= np.cos(np.radians(min_angle_deg))
    return np.argwhere(np.triu(same & (dd <= max_gap_m) & turned, 1))
