"""``hdmap export``: the published map of an area, fetched from the running publishers.

The area is a bounding box (min lon, min lat, max lon, max lat, WGS84 degrees). Its tiles
at the deployment's zoom are enumerated (:meth:`hdmap.geo.area.BBox.tiles`, edges included;
at most :data:`MAX_TILES`), and each tile's snapshot is asked for on
``hdmap/v1/map/<tile>/by/hdmap-export`` (:func:`schemas.keys.map_snapshot_for`: the export
has a snapshot budget of its own at the publishers, and a secured deployment's
``operator`` identity may query it). The publishers offer no index of the tiles they hold
(their stats count them; no query lists them), so the bounding box is required: there is
no "everything" export.

Snapshots are fetched :data:`WINDOW` at a time; a refusal for rate (the publisher's
per-client budget, ``[publisher.snapshots]``) is waited out as the publisher says and asked
again; a tile with no answer (no publisher serves it: outside every region, or the
publisher is down) is reported as unanswered. Everything is bounded by ``timeout_s``.
Landmarks outside the box (the tiles reach past it) are dropped, one row per id is kept
(the newest revision, should two publishers answer for one tile), and the rows are
formatted by :mod:`hdmap.ops.export_formats`, which says what is exported and what is not
(revoked landmarks are not: they are no longer in the map).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import zenoh

from hdmap.geo.area import BBox
from hdmap.geo.tiles import DEFAULT_ZOOM
from hdmap.ops.export_formats import ExportRow, export_rows, render
from schemas import DecodeError, ErrorReply, MapSnapshot, keys
from schemas.map import MapLandmarks, as_map_landmarks

CLIENT_ID = "hdmap-export"
"""The client id the export's snapshot queries are charged to at the publishers."""
WINDOW = 16
"""Snapshot queries in flight at once."""
MAX_TILES = 4096
"""A box of more tiles is refused (at zoom 16, 64 x 64 tiles: about 20 km x 20 km in
Helsinki; at the publisher's per-client rate of 20 snapshots/s, 3.5 minutes): export a
large area in parts."""
QUERY_TIMEOUT_S = 5.0
"""How long one snapshot query waits for its answers (less if the deadline is nearer)."""


@dataclass
class Fetched:
    """What the publishers answered for a set of tiles."""

    snapshots: dict[str, MapSnapshot] = field(default_factory=dict)
    unanswered: list[str] = field(default_factory=list)
    """Tiles no publisher answered (in time)."""
    errors: dict[str, str] = field(default_factory=dict)
    """Tiles answered with an error that does not pass (or a reply that did not decode)."""
    refusals: int = 0
    """Rate refusals waited out and asked again."""


def fetch_snapshots(
    session: zenoh.Session,
    tiles: Sequence[str],
    timeout_s: float = 60.0,
    client_id: str = CLIENT_ID,
    window: int = WINDOW,
    on_tile: Callable[[], None] | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> Fetched:
    """Each tile's snapshot (the newest version where several publishers answer), at most
    ``window`` queries at once, all within ``timeout_s``; ``on_tile`` after each tile
    settled (answered, failed or unanswered)."""
    deadline = clock() + timeout_s
    todo = list(tiles)
    out = Fetched()
    while todo:
        left = deadline - clock()
        if left <= 0:
            out.unanswered += todo
            break
        batch, todo = todo[:window], todo[window:]
        pending = [
            (
                tile,
                session.get(
                    keys.map_snapshot_for(client_id, tile),
                    timeout=min(QUERY_TIMEOUT_S, left),
                    consolidation=zenoh.ConsolidationMode.NONE,
                    target=zenoh.QueryTarget.ALL,
                ),
            )
            for tile in batch
        ]
        wait_s = 0.0
        for tile, replies in pending:
            best: MapSnapshot | None = None
            refusal: ErrorReply | None = None
            error = ""
            for reply in replies:  # ends when the query's timeout is over
                if reply.ok is not None:
                    try:
                        snap = MapSnapshot.from_bytes(reply.ok.payload.to_bytes())
                    except DecodeError as exc:
                        error = f"snapshot does not decode: {exc}"
                        continue
                    if best is None or snap.version > best.version:
                        best = snap
                    continue
                try:
                    err = ErrorReply.from_bytes(reply.err.payload.to_bytes())
                except DecodeError:
                    error = "an error reply that does not decode"
                    continue
                if err.code in ("rate", "busy"):
                    refusal = err
                else:
                    error = f"{err.code} ({err.field}): {err.message}"
            if best is not None:
                out.snapshots[tile] = best
            elif refusal is not None:  # our budget is spent: wait as told, then again
                out.refusals += 1
                todo.append(tile)
                wait_s = max(wait_s, refusal.retry_after_s or 0.1)
                continue
            elif error:
                out.errors[tile] = error
            else:
                out.unanswered.append(tile)
            if on_tile is not None:
                on_tile()
        if wait_s > 0:
            time.sleep(max(0.0, min(wait_s, deadline - clock())))
    return out


def landmarks_in(fetched: Fetched, bbox: BBox) -> MapLandmarks:
    """The landmarks of the fetched snapshots inside ``bbox``, one row per id (its newest
    revision), sorted by id."""
    parts = [s.landmarks for s in fetched.snapshots.values() if len(s.landmarks)]
    if not parts:
        return MapLandmarks.empty()
    lm = MapLandmarks.concat([as_map_landmarks(p) for p in parts])
    lm = lm.take(np.flatnonzero(bbox.contains(lm.lat, lm.lon)))
    order = np.lexsort((-lm.revision.astype(np.float64), lm.id))  # by id, newest first
    lm = lm.take(order)
    first = np.ones(len(lm), bool)
    first[1:] = lm.id[1:] != lm.id[:-1]
    return lm.take(np.flatnonzero(first))


@dataclass
class Export:
    """An export: its text, its rows and how the fetch went."""

    text: str
    rows: list[ExportRow]
    tiles: list[str]
    fetched: Fetched


def export_map(
    session: zenoh.Session,
    bbox: BBox,
    fmt: str,
    zoom: int = DEFAULT_ZOOM,
    timeout_s: float = 60.0,
    on_tile: Callable[[], None] | None = None,
    tiles: Sequence[str] | None = None,
) -> Export:
    """Fetch the box's tiles and format their landmarks in ``fmt`` (``geojson``, ``osm``,
    ``csv``), ``tiles`` those of the box at ``zoom`` unless given. ValueError beyond
    :data:`MAX_TILES` tiles."""
    tiles = bbox.tiles(zoom, MAX_TILES) if tiles is None else list(tiles)
    if len(tiles) > MAX_TILES:  # a list of the caller's
        raise ValueError(
            f"the box covers {len(tiles)} tiles at zoom {zoom}; at most {MAX_TILES}: "
            "export it in parts"
        )
    fetched = fetch_snapshots(session, tiles, timeout_s, on_tile=on_tile)
    rows = export_rows(landmarks_in(fetched, bbox))
    return Export(render(fmt, rows, bbox.as_tuple()), rows, tiles, fetched)
