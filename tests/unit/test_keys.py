"""schemas.keys: key shapes, and region selection checked by Zenoh's own key-expression algebra."""

from __future__ import annotations

import pytest
import zenoh

from schemas import keys


def test_key_shapes() -> None:
    assert keys.ROOT == "hdmap/v1"
    assert keys.region("120") == "120$*"
    assert keys.region("") == "*"
    assert keys.upload("veh-7") == "hdmap/v1/upload/veh-7"
    assert keys.upload("*") == "hdmap/v1/upload/*"
    assert keys.obs("1202") == "hdmap/v1/obs/1202"
    assert keys.assoc("1202") == "hdmap/v1/assoc/1202"
    assert keys.update("1202") == "hdmap/v1/update/1202"
    assert keys.map_delta("1202") == "hdmap/v1/map/1202/delta"
    assert keys.map_snapshot("1202") == "hdmap/v1/map/1202"
    assert keys.map_snapshot_for("veh-7", "1202") == "hdmap/v1/map/1202/by/veh-7"
    assert keys.log("obs", "ingest-1", "1202") == "hdmap/v1/log/obs/ingest-1/1202"
    assert keys.alive("matcher", "120+121", "m1") == "hdmap/v1/alive/matcher/120+121/m1"
    assert keys.stats("solver", "all", "s1") == "hdmap/v1/stats/solver/all/s1"


def test_chunk_helpers() -> None:
    k = keys.obs("1202102332")
    assert keys.last_chunk(k) == "1202102332"
    assert keys.chunk(k, 3) == "1202102332"
    assert keys.chunk(keys.map_delta("12"), 3) == "12"
    assert keys.last_chunk(keys.map_delta("12")) == "delta"


@pytest.mark.parametrize(
    "key",
    [
        keys.obs("1202"),
        keys.obs(keys.region("120")),
        keys.obs(keys.region("")),
        keys.map_delta(keys.region("1")),
        keys.upload("veh-7"),
        keys.alive("matcher", "120+121", "m1"),
        keys.log("assoc", "matcher-1", "0123"),
        keys.map_snapshot_for("veh-7", "1202"),
        keys.map_snapshot_for(keys.ANY, keys.region("120")),
    ],
)
def test_keys_are_canonical_zenoh_key_expressions(key: str) -> None:
    assert str(zenoh.KeyExpr(key)) == key
    assert str(zenoh.KeyExpr.autocanonize(key)) == key


def _ke(s: str) -> zenoh.KeyExpr:
    return zenoh.KeyExpr(s)


def test_region_selects_tiles_under_prefix() -> None:
    sel = _ke(keys.obs(keys.region("120")))
    assert sel.intersects(_ke(keys.obs("1202")))
    assert not sel.intersects(_ke(keys.obs("1302")))
    assert sel.includes(_ke(keys.obs("1202102332")))
    assert sel.includes(_ke(keys.obs("120")))  # $* also matches the empty suffix
    assert not sel.intersects(_ke(keys.obs("12")))
    assert not sel.intersects(_ke(keys.assoc("1202")))  # other stage
    assert not sel.intersects(_ke(keys.obs("1202") + "/x"))  # one chunk only


def test_whole_world_region() -> None:
    sel = _ke(keys.obs(keys.region("")))
    for qk in ("0", "1202", "3333333333333333"):
        assert sel.includes(_ke(keys.obs(qk)))


def test_snapshot_and_delta_keys_do_not_collide() -> None:
    # a subscriber to deltas of a region never receives snapshots and vice versa
    deltas = _ke(keys.map_delta(keys.region("120")))
    snaps = _ke(keys.map_snapshot(keys.region("120")))
    assert deltas.intersects(_ke(keys.map_delta("1202")))
    assert not deltas.intersects(_ke(keys.map_snapshot("1202")))
    assert snaps.intersects(_ke(keys.map_snapshot("1202")))
    assert not snaps.intersects(_ke(keys.map_delta("1202")))


def test_upload_queryable_covers_every_vehicle() -> None:
    q = _ke(keys.upload("*"))
    assert q.includes(_ke(keys.upload("veh-7")))
    assert not q.intersects(_ke(keys.obs("1202")))


def test_alive_and_stats_wildcards() -> None:
    every_matcher = _ke(f"{keys.ROOT}/alive/matcher/**")
    assert every_matcher.includes(_ke(keys.alive("matcher", "120+121", "m1")))
    assert not every_matcher.intersects(_ke(keys.alive("solver", "all", "s1")))
    assert _ke(keys.stats("*", "*", "*")).includes(_ke(keys.stats("solver", "all", "s1")))


def test_client_snapshot_keys_reach_their_own_queryable_only() -> None:
    anonymous = _ke(keys.map_snapshot(keys.region("120")))
    by_client = _ke(keys.map_snapshot_for(keys.ANY, keys.region("120")))
    mine = _ke(keys.map_snapshot_for("veh-7", "1202"))
    assert by_client.includes(mine) and not anonymous.intersects(mine)
    assert not by_client.intersects(_ke(keys.map_snapshot("1202")))
    assert not by_client.intersects(_ke(keys.map_snapshot_for("veh-7", "1302")))  # other region
    # a subscriber to deltas never receives a snapshot reply, even of a client named 'delta'
    deltas = _ke(keys.map_delta(keys.region("120")))
    assert not deltas.intersects(mine)
    assert not deltas.intersects(_ke(keys.map_snapshot_for("delta", "1202")))
    # the ACL's per-vehicle right covers its own client key of every tile, no other client's
    own = _ke(keys.map_snapshot_for("veh-7", keys.ANY))
    assert own.includes(mine) and not own.intersects(_ke(keys.map_snapshot_for("veh-8", "1202")))


@pytest.mark.parametrize(
    "key,want",
    [
        ("hdmap/v1/map/1202", ("1202", keys.ANONYMOUS)),
        ("hdmap/v1/map/1202/by/veh-7", ("1202", "veh-7")),
        ("hdmap/v1/map/12a/by/veh-7", ("12a", "veh-7")),  # the tile is the publisher's to check
        ("hdmap/v1/map/1202/by/*", ("", keys.ANONYMOUS)),  # a wildcard client
        ("hdmap/v1/map/1202/by/**", ("", keys.ANONYMOUS)),
        ("hdmap/v1/map/1202/by/v$*", ("", keys.ANONYMOUS)),
        ("hdmap/v1/map/1202/by/" + "x" * 65, ("", keys.ANONYMOUS)),  # not an id
        ("hdmap/v1/map/1202/by/veh-7/x", ("", keys.ANONYMOUS)),
        ("hdmap/v1/map/1202/from/veh-7", ("", keys.ANONYMOUS)),
        ("hdmap/v1/map/1202/delta", ("", keys.ANONYMOUS)),
        ("hdmap/v1/map/**", ("**", keys.ANONYMOUS)),  # no quadkey: the publisher refuses it
        ("hdmap/v1/**", ("", keys.ANONYMOUS)),
        ("hdmap/v1/obs/1202", ("", keys.ANONYMOUS)),
        ("", ("", keys.ANONYMOUS)),
    ],
)
def test_snapshot_request_parses_both_forms(key: str, want: tuple[str, str]) -> None:
    assert keys.snapshot_request(key) == want
    assert keys.snapshot_tile(key) == want[0]
