"""A real town: central Helsinki's streets and traffic-sign posts from OpenStreetMap.

Data © OpenStreetMap contributors, ODbL 1.0 (``fleetsim/data/helsinki.json``,
extracted once by ``scripts/extract_helsinki.py``). ``docs/helsinki.md`` has the
details and counts; ``python -m fleetsim.osm_town [out.png]`` prints (and plots) them.

Road graph: the OSM drivable ways in the ENU frame of the data's centre, one
directed edge per segment and allowed direction (``oneway`` respected), reduced
to where a random walk without U-turns never gets stuck (largest strongly
connected component, cul-de-sacs removed), pass-through nodes dropped where the
road moves < 0.5 m.

What OSM lacks is filled in per sign:

- class: the first Finnish code of :data:`FI_CLASSES` on the post (panels top
  first), or ``highway=give_way``/``stop``; else drawn uniformly (seeded).
- position: the OSM node; one on the centreline goes to the right-hand roadside
  of its traffic, one closer than 3.5 m is pushed out on its side, both to
  ``lane_offset + U(2.5, 4)`` m. Signs > 25 m from every road, or moved into
  another road, are dropped.
- facing: against the traffic of the nearest segment (its one-way direction, or
  the one for which the sign is on the right; on the centreline: the traffic
  heading for the nearer junction), +- 8 deg.
- mounting height: U(2.0, 2.8) m.

Added (not in OSM): :data:`CORNER_PAIRS` same-class pairs at junctions, one sign facing
each of two crossing streets, 5-10 m apart (:func:`fleetsim.world.corner_pairs`; rows
after the OSM signs, ``osm_id`` -1): the case of two landmarks of one class that only
their facing tells apart.

Draws are made for every sign of the extract in OSM id order, so a sign keeps
them whatever ``bbox`` or ``max_signs`` select.

>>> w = helsinki_town(max_signs=50)
>>> len(w.signs), w.signs.id[:3].tolist()
(50, [0, 1, 2])
"""

from __future__ import annotations

import itertools
import json
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from fleetsim.world import Signs, World, corner_pairs, tile_border_distance
from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.signs import CATALOG

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

DATA_FILE = Path(__file__).with_name("data") / "helsinki.json"
ATTRIBUTION = "© OpenStreetMap contributors, ODbL 1.0"
H0 = 20.0
"""Ellipsoidal height of the anchor, m (geoid ~17.5 m + ground a few m)."""
MAX_ROAD_DISTANCE_M = 25.0
ON_ROAD_M = 0.5
SIMPLIFY_M = 0.5
KERB_M = 3.5
LATERAL_M = (2.5, 4.0)
HEIGHT_M = (2.0, 2.8)
FACING_JITTER_DEG = 8.0
CORNER_PAIRS = 6
"""Same-class pairs added at junctions, one sign facing each of two crossing streets
(:func:`fleetsim.world.corner_pairs`): up to 6 in any selection (the whole extract or a
bbox; fewer where it has fewer junctions that fit: 5 in the fleet evaluation's area at
seed 0)."""

FI_CLASSES: dict[str, str] = {
    "FI:142": "road_works",  # tietyö (not in this extract)
    "FI:152": "children",  # lapsia
    "FI:211": "priority_road",  # etuajo-oikeutettu tie
    "FI:231": "give_way",  # väistämisvelvollisuus risteyksessä
    "FI:232": "stop",  # pakollinen pysäyttäminen
    "FI:331": "no_entry",  # kielletty ajosuunta
    **dict.fromkeys(("FI:332", "FI:333", "FI:334"), "no_turn"),  # no left/right/U-turn
    "FI:371": "no_stopping",  # pysäyttäminen kielletty
    "FI:372": "no_parking",  # pysäköinti kielletty
    "FI:373": "no_parking",  # pysäköintikieltoalue (zone sign with the same disc)
    "FI:417": "keep_right",  # liikenteenjakaja (not with a [left] arrow)
    **dict.fromkeys(("FI:421", "FI:422", "FI:423", "FI:424"), "cycle_path"),  # (+ foot)
    "FI:511": "pedestrian_crossing",  # suojatie
    "FI:521": "parking",  # pysäköintipaikka (also 521a/b/c)
    "FI:531": "bus_stop",  # linja-autopysäkki
    "FI:551": "one_way",  # yksisuuntainen tie
}
"""Finnish sign codes (the pre-2020 numbering used in this extract) -> our classes.

Speed limits are read from the value: ``FI:361[30]`` (limit) and ``FI:363[30]``
(zone) -> ``speed_limit_30``, likewise 40 and 50.
"""
_CODE = re.compile(r"^(FI:\d{3})([a-z]?)((?:\[[^\]]*\])*)$")
_SPEED = {"30": "speed_limit_30", "40": "speed_limit_40", "50": "speed_limit_50"}
_SIGN_KEY = re.compile(r"^traffic_sign(?::(\d+))?$")


def classify_value(value: str) -> tuple[str, str] | None:
    """(class name, code) of one panel value such as ``FI:363[30]``; None if not ours.

    >>> classify_value("FI:363[40]"), classify_value("FI:521c[left]"), classify_value("FI:871")
    (('speed_limit_40', 'FI:363'), ('parking', 'FI:521'), None)
    """
    m = _CODE.match(value.strip())
    if not m:
        return None
    code, args = m.group(1), m.group(3)
    if code in ("FI:361", "FI:363"):
        name = _SPEED.get(args[1:-1].strip()) if args.count("[") == 1 else None
        return (name, code) if name else None
    if code == "FI:417" and "left" in args:
        return None
    return (FI_CLASSES[code], code) if code in FI_CLASSES else None


def classify(tags: dict[str, str]) -> tuple[str, str] | None:
    """(class name, code) of a sign post from its OSM tags: the first panel we know."""
    keys = sorted((int(m.group(1) or 1), k) for k in tags if (m := _SIGN_KEY.match(k)) is not None)
    for _, key in keys:
        for value in tags[key].split(";"):
            hit = classify_value(value)
            if hit:
                return hit
    hw = tags.get("highway")
    return (hw, f"highway={hw}") if hw in ("give_way", "stop") else None


@lru_cache(maxsize=1)
def load_extract(path: Path = DATA_FILE) -> dict:
    """The extract (nodes, ways, signs, attribution, source) as parsed JSON."""
    return json.loads(Path(path).read_text(encoding="utf-8"))


@dataclass(frozen=True)
class OsmTown:
    """The World and, per sign row, where its class came from."""

    world: World
    osm_id: IntArray
    """OSM node id of each sign row."""
    code: tuple[str, ...]
    """The OSM code that gave the class ('' when the class was drawn)."""
    placement: NDArray[np.int8]
    """0: at its OSM node; 1: pushed out from < 3.5 m; 2: moved off the centreline; 3: not
    from OSM, a corner pair added by the simulator (``osm_id`` -1)."""
    n_far: int
    """Signs (in the bbox) dropped for being farther than 25 m from every road."""
    n_in_road: int
    """Signs dropped because moving them left them < 3.5 m from another road."""

    @property
    def mapped(self) -> NDArray[np.bool_]:
        return np.array([c != "" for c in self.code], bool)


def _prune(n: int, e: IntArray) -> IntArray:
    """Largest strongly connected part without cul-de-sacs (only a U-turn leads on)."""
    while len(e):
        g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        _, lab = connected_components(g, directed=True, connection="strong")
        big = np.bincount(lab[e.ravel()]).argmax()
        e = e[(lab[e[:, 0]] == big) & (lab[e[:, 1]] == big)]
        key = e[:, 0] * n + e[:, 1]
        has_back = np.isin(e[:, 1] * n + e[:, 0], key)
        out = np.bincount(e[:, 0], minlength=n)
        dead = out[e[:, 1]] - has_back == 0
        if not dead.any():
            break
        e = e[~dead]
    return e


def _road_graph(data: dict, keep: NDArray[np.bool_]) -> IntArray:
    """Directed edges (global node indices) of the ways, restricted to ``keep`` nodes."""
    pairs: list[tuple[int, int]] = []
    for w in data["ways"]:
        nd = w["nodes"]
        for a, b in itertools.pairwise(nd):
            if a == b or not (keep[a] and keep[b]):
                continue
            if w["oneway"] >= 0:
                pairs.append((a, b))
            if w["oneway"] <= 0:
                pairs.append((b, a))
    e = np.unique(np.array(pairs, np.int64).reshape(-1, 2), axis=0)
    return _prune(len(keep), e)


def _simplify(nodes: Array, e: IntArray, tol: float = SIMPLIFY_M) -> IntArray:
    """Drop pass-through nodes (two neighbours) whose removal moves no road point > ``tol``."""
    out: dict[int, set[int]] = {v: set() for v in range(len(nodes))}
    inn: dict[int, set[int]] = {v: set() for v in range(len(nodes))}
    for a, b in e.tolist():
        out[a].add(b)
        inn[b].add(a)
    via: dict[tuple[int, int], list[int]] = {}  # nodes dropped along each undirected edge
    for v in range(len(nodes)):
        nb = out[v] | inn[v]
        if len(nb) != 2:
            continue
        p, c = sorted(nb)
        fw, bw = v in out[p], v in out[c]
        if fw != (c in out[v]) or bw != (p in out[v]) or c in out[p] | inn[p]:
            continue  # not a pass-through, or p and c already joined
        pts = [v, *via.get((min(p, v), max(p, v)), []), *via.get((min(v, c), max(v, c)), [])]
        t, q = nodes[c] - nodes[p], nodes[pts] - nodes[p]
        u = np.clip(q @ t / (t @ t), 0.0, 1.0)
        if np.linalg.norm(q - u[:, None] * t, axis=1).max() >= tol:
            continue
        for x in (p, c):
            out[x].discard(v)
            inn[x].discard(v)
        out[v].clear()
        inn[v].clear()
        if fw:
            out[p].add(c)
            inn[c].add(p)
        if bw:
            out[c].add(p)
            inn[p].add(c)
        via[(p, c)] = pts
    return np.array(sorted((a, b) for a in out for b in out[a]), np.int64).reshape(-1, 2)


def _nearest_segments(p: Array, a: Array, b: Array) -> tuple[IntArray, Array, Array]:
    """Per point: nearest segment, foot point (N, 2) and distance (chunked brute force)."""
    k = np.empty(len(p), np.int64)
    foot = np.empty((len(p), 2))
    t = b - a
    tt = np.maximum(np.sum(t * t, axis=1), 1e-12)
    for s in range(0, len(p), 256):
        q = p[s : s + 256, None, :]
        u = np.clip(np.sum((q - a) * t, axis=-1) / tt, 0.0, 1.0)
        f = a + u[..., None] * t
        d2 = np.sum((q - f) ** 2, axis=-1)
        j = np.argmin(d2, axis=1)
        k[s : s + 256] = j
        foot[s : s + 256] = f[np.arange(len(j)), j]
    return k, foot, np.linalg.norm(p - foot, axis=1)


def build_helsinki(
    seed: int = 0,
    *,
    max_signs: int | None = None,
    bbox: tuple[float, float, float, float] | None = None,
    lane_offset_m: float = 1.75,
    corner_pairs_n: int | None = None,
) -> OsmTown:
    """The Helsinki town with the provenance of its sign classes; see :func:`helsinki_town`.

    ``corner_pairs_n`` corner pairs are added (None: :data:`CORNER_PAIRS`, none with
    ``max_signs``, a subset of the OSM signs for small tests)."""
    if corner_pairs_n is None:
        corner_pairs_n = CORNER_PAIRS if max_signs is None else 0
    data = load_extract()
    lat = np.asarray(data["nodes"]["lat_e7"], np.int64) / 1e7
    lon = np.asarray(data["nodes"]["lon_e7"], np.int64) / 1e7
    sg = data["signs"]
    s_lat = np.array([s["lat_e7"] for s in sg], np.int64) / 1e7
    s_lon = np.array([s["lon_e7"] for s in sg], np.int64) / 1e7
    south, west, north, east = bbox or (-90.0, -180.0, 90.0, 180.0)
    s_keep = (s_lat >= south) & (s_lat <= north) & (s_lon >= west) & (s_lon <= east)
    edges_g = _road_graph(data, (lat >= south) & (lat <= north) & (lon >= west) & (lon <= east))
    used = np.unique(edges_g)
    if used.size == 0:
        raise ValueError(f"no drivable roads in bbox {bbox}")
    lat0 = round(float(lat[used].min() + lat[used].max()) / 2.0, 6)
    lon0 = round(float(lon[used].min() + lon[used].max()) / 2.0, 6)
    frame = EnuFrame(lat0, lon0, H0)
    nodes = frame.from_geodetic(lat[used], lon[used], np.full(used.size, H0))[:, :2]
    edges = _simplify(nodes, np.searchsorted(used, edges_g))
    used = np.unique(edges)
    nodes, edges = nodes[used], np.searchsorted(used, edges)

    # Per-sign draws over the whole extract, in its (OSM id) order.
    rng = np.random.default_rng(seed)
    drawn_cls = CATALOG.codes[rng.integers(CATALOG.codes.size, size=len(sg))]
    z = rng.uniform(*HEIGHT_M, len(sg))
    jitter = rng.uniform(-FACING_JITTER_DEG, FACING_JITTER_DEG, len(sg))
    lateral = lane_offset_m + rng.uniform(*LATERAL_M, len(sg))

    # Undirected segments and their allowed directions.
    und = np.unique(np.sort(edges, axis=1), axis=0)
    key = edges[:, 0] * len(nodes) + edges[:, 1]
    fwd = np.isin(und[:, 0] * len(nodes) + und[:, 1], key)
    bwd = np.isin(und[:, 1] * len(nodes) + und[:, 0], key)
    a, b = nodes[und[:, 0]], nodes[und[:, 1]]
    tang = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)

    rows = np.flatnonzero(s_keep)
    p = frame.from_geodetic(s_lat[rows], s_lon[rows], np.full(rows.size, H0))[:, :2]
    k, foot, dist = _nearest_segments(p, a, b)
    ok = dist <= MAX_ROAD_DISTANCE_M
    rows, p, k, foot, dist = rows[ok], p[ok], k[ok], foot[ok], dist[ok]
    t = tang[k]
    cross = t[:, 0] * (p - foot)[:, 1] - t[:, 1] * (p - foot)[:, 0]  # > 0: left of a->b
    on_road = dist < ON_ROAD_M
    # Travel direction the sign is for: sign on the right of travel on two-way roads.
    sgn = np.where(fwd[k] & bwd[k], np.where(cross <= 0.0, 1.0, -1.0), np.where(fwd[k], 1.0, -1.0))
    # On the centreline of a two-way road: for the traffic heading for the nearer junction.
    i = np.flatnonzero(on_road & fwd[k] & bwd[k])
    rel = nodes[np.bincount(und.ravel(), minlength=len(nodes)) >= 3][None] - foot[i, None]
    ahead, dj = np.einsum("mjk,mk->mj", rel, t[i]) > 0.0, np.linalg.norm(rel, axis=-1)
    near = np.where(ahead, dj, np.inf).min(1, initial=np.inf)
    sgn[i] = np.where(near <= np.where(ahead, np.inf, dj).min(1, initial=np.inf), 1.0, -1.0)
    d = t * sgn[:, None]
    right = np.column_stack([d[:, 1], -d[:, 0]])
    # Unit normal from the centreline toward the side the sign stands on.
    away = np.where(on_road[:, None], right, (p - foot) / np.maximum(dist, 1e-9)[:, None])
    moved = dist < KERB_M
    p = np.where(moved[:, None], foot + away * lateral[rows, None], p)
    fits = ~moved | (_nearest_segments(p, a, b)[2] >= KERB_M - 1e-6)
    az = np.degrees(np.arctan2(-d[:, 0], -d[:, 1])) + jitter[rows]

    found = [classify(sg[r]["tags"]) for r in rows]
    cls = np.array([CATALOG.code(f[0]) if f else -1 for f in found], np.int64).reshape(-1)
    cls = np.where(cls >= 0, cls, drawn_cls[rows])
    codes = tuple(f[1] if f else "" for f in found)
    placement = np.where(on_road, 2, np.where(moved, 1, 0)).astype(np.int8)
    pick = np.flatnonzero(fits)
    if max_signs is not None and max_signs < pick.size:
        pick = np.sort(np.random.default_rng([seed, 1]).choice(pick, max_signs, replace=False))
    # Same-class pairs at junctions facing the two crossing streets (OSM has no such
    # detail): drawn on the graph of the selection with their own generator.
    corners = corner_pairs(
        nodes,
        edges,
        corner_pairs_n,
        np.random.default_rng([seed, 2]),
        CATALOG.codes,
        lane_offset_m=lane_offset_m,
        min_leg_m=10.0,
        keep_clear=p[pick],
        keep_clear_cls=cls[pick],
        clear_m=3.0,
    )
    nc = len(corners.xy)
    signs = Signs.build(
        np.r_[cls[pick], corners.sign_class],
        np.column_stack(
            [np.vstack([p[pick], corners.xy]), np.r_[z[rows[pick]], _corner_heights(seed, nc)]]
        ),
        np.r_[az[pick], corners.facing_az_deg] % 360.0,
    )
    world = World(frame, nodes, edges, signs, lane_offset_m)
    osm_id = np.r_[np.array([sg[r]["id"] for r in rows[pick]], np.int64), np.full(nc, -1)]
    n_far, n_in_road = int(s_keep.sum() - ok.sum()), int((~fits).sum())
    return OsmTown(
        world,
        osm_id.astype(np.int64),
        tuple(codes[i] for i in pick) + ("",) * nc,
        np.r_[placement[pick], np.full(nc, 3, np.int8)].astype(np.int8),
        n_far,
        n_in_road,
    )


def _corner_heights(seed: int, n: int) -> Array:
    """Mounting heights of ``n`` added corner signs (their own generator)."""
    return np.random.default_rng([seed, 3]).uniform(*HEIGHT_M, n)


def helsinki_town(
    seed: int = 0,
    *,
    max_signs: int | None = None,
    bbox: tuple[float, float, float, float] | None = None,
) -> World:
    """Central Helsinki from OpenStreetMap (see the module docstring).

    ``bbox`` = (south, west, north, east) degrees keeps the roads and signs inside
    it; ``max_signs`` keeps a random (seeded) subset of the signs. Sign ids are
    0..N-1 in OSM node id order.
    """
    return build_helsinki(seed, max_signs=max_signs, bbox=bbox).world


def same_class_pairs(world: World, lo: float = 3.0, hi: float = 10.0) -> IntArray:
    """(K, 2) sign rows i < j of the same class between ``lo`` and ``hi`` m apart."""
    s = world.signs
    dd = np.linalg.norm(s.position[:, None, :2] - s.position[None, :, :2], axis=-1)
    same = s.sign_class[:, None] == s.sign_class[None, :]
    return np.argwhere(np.triu(same & (dd >= lo) & (dd <= hi), 1))


def town_stats(town: OsmTown) -> dict[str, float | int | dict[str, int]]:
    """The counts quoted in docs/helsinki.md."""
    w = town.world
    s = w.signs
    names = [CATALOG.by_code(c).name for c in s.sign_class]
    seg = np.unique(np.sort(w.edges, axis=1), axis=0)
    length = np.linalg.norm(w.nodes[seg[:, 0]] - w.nodes[seg[:, 1]], axis=1).sum()
    oneway = len(seg) - (len(w.edges) - len(seg))
    return {
        "signs": len(s),
        "mapped": int(town.mapped.sum()),
        "drawn": int((~town.mapped).sum()),
        "classes": len(set(names)),
        "per_class": {n: names.count(n) for n in sorted(set(names))},
        "placed_at_osm_node": int((town.placement == 0).sum()),
        "pushed_to_roadside": int((town.placement == 1).sum()),
        "moved_off_centreline": int((town.placement == 2).sum()),
        "dropped_beyond_25m": town.n_far,
        "dropped_in_road_after_move": town.n_in_road,
        "same_class_pairs_3_10m": len(same_class_pairs(w)),
        "near_tile_border_15m": int((tile_border_distance(w, s.position[:, :2]) < 15.0).sum()),
        "road_km": round(float(length) / 1e3, 2),
        "nodes": len(w.nodes),
        "edges": len(w.edges),
        "one_way_segments": int(oneway),
    }


def plot_town(world: World, out_png: str | Path) -> None:
    """Roads, and signs with their facing coloured by class (Agg, no pyplot state)."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 13), dpi=100)
    ax = FigureCanvasAgg(fig).figure.add_subplot(1, 1, 1, aspect="equal")
    for road in world.roads():
        ax.plot(road[:, 0], road[:, 1], color="0.7", lw=1.5, zorder=0)
    s = world.signs
    for c in np.unique(s.sign_class):
        m, col, name = s.sign_class == c, colormaps["tab20"](c - 1), CATALOG.by_code(c).name
        xy, f = s.position[m], s.facing[m]
        ax.quiver(xy[:, 0], xy[:, 1], f[:, 0], f[:, 1], color=col, scale=60, width=0.002)
        ax.scatter(xy[:, 0], xy[:, 1], s=10, color=col, label=f"{name} ({m.sum()})")
    ax.set(xlabel="East (m)", ylabel="North (m)", title=f"Helsinki, {len(s)} signs. {ATTRIBUTION}")
    ax.legend(fontsize=7, loc="upper left", markerscale=2)
    fig.savefig(str(out_png), bbox_inches="tight")


if __name__ == "__main__":
    import sys

    town = build_helsinki()
    print(json.dumps(town_stats(town), indent=1))
    if len(sys.argv) > 1:
        plot_town(town.world, sys.argv[1])
