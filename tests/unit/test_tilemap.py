"""Publisher tile maps: versions, coalescing, stale revisions, moves, snapshots.

The same tests run against a file database and an in-memory one (state behind one
interface, each backend tested).
"""

from __future__ import annotations

import numpy as np
import pytest

from hdmap.runtime.store import connect, transaction
from schemas import Landmarks, LandmarkUpdates, MapDelta, MapSnapshot, Removals
from services.publisher.tilemap import TileMaps, read_snapshot, snapshot


def lms(ids, revs, lat=60.17, status=1) -> Landmarks:
    n = len(ids)
    return Landmarks(
        id=np.array(ids, np.uint64),
        sign_class=np.full(n, 4, np.uint16),
        lat=np.full(n, lat),
        lon=np.full(n, 24.94),
        h=np.full(n, 22.0),
        cov=np.tile([1.0, 0.1, 0.0, 1.0, 0.0, 2.0], (n, 1)),
        status=np.full(n, status, np.uint8),
        n_obs=np.full(n, 10, np.uint32),
        n_passes=np.full(n, 3, np.uint32),
        revision=np.array(revs, np.uint64),
        updated_at=np.full(n, 1.7e9),
        source_time=np.full(n, 1.7e9),
    )


def upd(ids=(), revs=(), removed=(), rrevs=(), lat=60.17) -> LandmarkUpdates:
    return LandmarkUpdates(
        lms(list(ids), list(revs), lat),
        Removals(np.array(removed, np.uint64), np.array(rrevs, np.uint64)),
    )


@pytest.fixture(params=["file", "memory"])
def conn(request, tmp_path):
    c = connect(tmp_path / "p.sqlite") if request.param == "file" else connect(":memory:")
    yield c
    c.close()


def flush(conn, maps):
    with transaction(conn):
        return maps.flush(now=1.7e9)


def test_versions_grow_by_one_per_change_set(conn):
    maps = TileMaps(conn)
    maps.apply("A", upd([1, 2], [1, 1]))
    maps.apply("A", upd([1], [2]))
    (d,) = flush(conn, maps)
    assert (d.tile, d.from_version, d.to_version) == ("A", 0, 1)
    assert sorted(d.upserts.id.tolist()) == [1, 2]
    assert d.upserts.revision[d.upserts.id.tolist().index(1)] == 2  # coalesced: newest only
    assert flush(conn, maps) == []
    maps.apply("A", upd([2], [5]))
    (d2,) = flush(conn, maps)
    assert (d2.from_version, d2.to_version) == (1, 2)


def test_stale_revisions_are_ignored(conn):
    maps = TileMaps(conn)
    maps.apply("A", upd([1], [3]))
    flush(conn, maps)
    assert maps.apply("A", upd([1], [2])) == 0
    assert maps.apply("A", upd([1], [3])) == 0
    assert flush(conn, maps) == []


def test_move_between_tiles_removes_from_the_old_one(conn):
    maps = TileMaps(conn)
    maps.apply("A", upd([1], [1]))
    flush(conn, maps)
    maps.apply("B", upd([1], [2]))
    maps.apply("A", upd(removed=[1], rrevs=[2]))  # the solver's removal, after the upsert
    deltas = {d.tile: d for d in flush(conn, maps)}
    assert deltas["A"].removed.id.tolist() == [1]
    assert deltas["B"].upserts.id.tolist() == [1]
    assert len(snapshot(conn, "A").landmarks) == 0
    assert snapshot(conn, "B").landmarks.id.tolist() == [1]


def test_removal_first_then_upsert_elsewhere(conn):
    maps = TileMaps(conn)
    maps.apply("A", upd([1], [1]))
    flush(conn, maps)
    maps.apply("A", upd(removed=[1], rrevs=[2]))
    maps.apply("B", upd([1], [2]))
    deltas = {d.tile: d for d in flush(conn, maps)}
    assert deltas["A"].removed.id.tolist() == [1]
    assert deltas["B"].upserts.id.tolist() == [1]


def test_snapshot_matches_the_deltas(conn):
    maps = TileMaps(conn)
    held: dict[int, int] = {}
    version = 0
    rng = np.random.default_rng(3)
    rev = dict.fromkeys(range(1, 9), 0)
    for _ in range(30):
        ids = rng.choice(8, size=3, replace=False) + 1
        for i in ids:
            rev[int(i)] += 1
        maps.apply("A", upd(ids.tolist(), [rev[int(i)] for i in ids]))
        if rng.random() < 0.3:
            gone = int(rng.integers(1, 9))
            rev[gone] += 1
            maps.apply("A", upd(removed=[gone], rrevs=[rev[gone]]))
        for d in flush(conn, maps):
            assert d.from_version == version
            version = d.to_version
            held.update(zip(d.upserts.id.tolist(), d.upserts.revision.tolist(), strict=True))
            for i in d.removed.id.tolist():
                held.pop(i, None)
    snap = snapshot(conn, "A")
    assert snap.version == version
    assert (
        dict(zip(snap.landmarks.id.tolist(), snap.landmarks.revision.tolist(), strict=True)) == held
    )


def test_unknown_tile_snapshot_is_empty_version_zero(conn):
    TileMaps(conn)
    snap = snapshot(conn, "0123")
    assert (snap.version, len(snap.landmarks)) == (0, 0)


def test_a_row_the_schema_refuses_is_quarantined_not_published(conn):
    maps = TileMaps(conn)
    maps.apply("0123", upd([1, 2, 3], [1, 1, 1]))
    with transaction(conn):  # damage on disk: a latitude no decoder accepts, a cut blob
        conn.execute("UPDATE current SET lat=6000 WHERE id=2")
        conn.execute("UPDATE current SET cov=x'00' WHERE id=3")
    (d,) = flush(conn, maps)
    assert d.upserts.id.tolist() == [1] and maps.quarantined == 2
    assert MapDelta.from_bytes(d.to_bytes()).upserts.id.tolist() == [1]
    rows = conn.execute("SELECT id, field FROM quarantine ORDER BY id").fetchall()
    assert rows == [(2, "lat"), (3, "cov")]
    assert maps.counts()["quarantine"] == 2
    # a later valid revision of the landmark is published as usual
    maps.apply("0123", upd([2], [2]))
    (d2,) = flush(conn, maps)
    assert d2.upserts.id.tolist() == [2] and maps.quarantined == 0


def test_a_snapshot_withholds_rows_damaged_after_publishing(conn):
    maps = TileMaps(conn)
    maps.apply("0123", upd([1, 2], [1, 1]))
    flush(conn, maps)
    with transaction(conn):
        conn.execute("UPDATE published SET lat=6000 WHERE id=2")
    snap, withheld = read_snapshot(conn, "0123")
    assert withheld == 1 and snap.landmarks.id.tolist() == [1]
    assert MapSnapshot.from_bytes(snap.to_bytes()).landmarks.id.tolist() == [1]
