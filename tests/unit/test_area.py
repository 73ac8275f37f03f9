"""hdmap.geo.area: ``--bbox`` parsing, the tiles of a box (counted as mercantile lists them,
refused beyond a limit), the points inside it, the box around tiles."""

from __future__ import annotations

import re

import mercantile
import numpy as np
import pytest

from hdmap.geo.area import BBox


def test_parse_refuses_what_it_cannot_use_and_names_the_option() -> None:
    bad = (
        "1,2,3", "a,b,c,d", "10,60,9,61", "25,60,24,61", "10,61,11,60", "10,86,11,87",
        "0,89,1,90", "nan,1,2,3", "inf,60,25,61", "181,60,182,61", "1,2,3,4,5",
    )  # fmt: skip
    for text in bad:
        with pytest.raises(ValueError, match=f"^--bbox {re.escape(repr(text))}: "):
            BBox.parse(text)
    with pytest.raises(ValueError, match=r"^area '1,2,3': need minlon,minlat,maxlon,maxlat$"):
        BBox.parse("1,2,3", name="area")
    box = BBox.parse("24.93,60.16,24.96,60.18")
    assert box.as_tuple() == (24.93, 60.16, 24.96, 60.18)


def test_tiles_and_their_limit() -> None:
    box = BBox.parse("24.93,60.165,24.95,60.175")
    tiles = box.tiles(16, limit=4096)
    assert tiles and all(len(t) == 16 for t in tiles) and tiles == sorted(tiles)
    many = len(box.tiles(18, limit=10**6))
    with pytest.raises(ValueError, match=f"covers {many} tiles at zoom 18; at most 10"):
        box.tiles(18, limit=10)
    assert box.tiles(16, limit=len(tiles)) == tiles


@pytest.mark.parametrize(
    "box",
    [
        BBox(24.93, 60.165, 24.95, 60.175),
        BBox(*mercantile.bounds(mercantile.Tile(37_000, 18_000, 16))),  # one tile's edges
        BBox(-0.01, -0.01, 0.01, 0.01),
        BBox(-180.0, -85.0511287798066, -179.99, -85.05),
        BBox(179.99, 85.05, 180.0, 85.0511287798066),
    ],
)
def test_the_count_is_what_mercantile_lists(box: BBox) -> None:
    listed = {mercantile.quadkey(t) for t in mercantile.tiles(*box.as_tuple(), 16)}
    assert box.tile_count(16) == len(listed)
    assert set(box.tiles(16, limit=len(listed))) == listed
    with pytest.raises(ValueError, match=f"covers {len(listed)} tiles at zoom 16; at most"):
        box.tiles(16, limit=len(listed) - 1)


def test_the_box_of_one_tile_covers_that_tile_alone() -> None:
    qk = "1201202110133102"
    box = BBox.of_tiles([qk])
    assert box is not None and box.tiles(16, limit=1) == [qk]


def test_contains_is_vectorised_and_includes_the_edges() -> None:
    box = BBox.parse("24.93,60.16,24.96,60.18")
    lat = np.array([60.17, 60.2, 60.16, 60.17])
    lon = np.array([24.94, 24.94, 24.96, 24.92])
    assert box.contains(lat, lon).tolist() == [True, False, True, False]
    assert box.contains(60.17, 24.94).shape == ()


def test_the_box_around_tiles() -> None:
    box = BBox.parse("24.93,60.165,24.95,60.175")
    around = BBox.of_tiles(box.tiles(16, limit=4096))
    assert around is not None
    assert around.west <= box.west and around.south <= box.south
    assert around.east >= box.east and around.north >= box.north
    corners = [mercantile.bounds(mercantile.quadkey_to_tile(q)) for q in box.tiles(16, 4096)]
    assert around.as_tuple() == (
        min(b.west for b in corners),
        min(b.south for b in corners),
        max(b.east for b in corners),
        max(b.north for b in corners),
    )
    assert BBox.of_tiles([]) is None
