"""Corruption as a permanent fault: the store's check at open and in transactions, a
service that stops on it (exit code, one line naming the file), the ``permanent`` flag
of ``UploadAck`` and the vehicle's backoff on it."""

from __future__ import annotations

import contextlib
import logging
import sqlite3
from pathlib import Path

import msgpack
import numpy as np
import pytest

from fleetsim.synthetic import make_observations
from hdmap.runtime.service import PermanentFault, Service, ServiceOptions
from hdmap.runtime.store import (
    EXIT_CORRUPT,
    DatabaseCorrupt,
    StorageError,
    check_integrity,
    connect,
    transaction,
)
from schemas import DecodeError, ObservationBatch, UploadAck
from tests.support import Clock
from vehicle.uploader import PERMANENT_BACKOFF_MAX_S, PERMANENT_BACKOFF_MIN_S, Uploader

PAGE = 4096


def filled(path: Path) -> Path:
    """A closed database of a few dozen pages: a table with an index, like ingest's."""
    db = connect(path)
    db.execute("CREATE TABLE seen (v TEXT, id INTEGER, PRIMARY KEY (v, id)) WITHOUT ROWID")
    db.execute("CREATE TABLE other (k INTEGER PRIMARY KEY, body BLOB)")
    with transaction(db):
        db.executemany("INSERT INTO seen VALUES ('veh', ?)", [(i,) for i in range(5000)])
        db.executemany("INSERT INTO other(body) VALUES (?)", [(b"x" * 100,)] * 500)
    db.close()
    return path


def pages_of(path: Path, table: str) -> list[int]:
    with contextlib.closing(sqlite3.connect(path)) as c:
        return [r[0] for r in c.execute("SELECT pageno FROM dbstat WHERE name=?", (table,))]


def overwrite(path: Path, pages: list[int]) -> None:
    with open(path, "r+b") as f:
        for pg in pages:
            f.seek((pg - 1) * PAGE)
            f.write(b"\xa5" * PAGE)


def test_a_sound_database_passes_the_check(tmp_path):
    db = connect(filled(tmp_path / "a.sqlite"), check=True)
    check_integrity(db, tmp_path / "a.sqlite")
    db.close()


def test_a_damaged_page_fails_the_check_at_open_naming_the_file(tmp_path):
    path = filled(tmp_path / "a.sqlite")
    pages = pages_of(path, "other")
    overwrite(path, [pages[len(pages) // 2]])
    connect(path).close()  # opening alone does not read the damaged page
    with pytest.raises(DatabaseCorrupt) as exc:
        connect(path, check=True)
    assert exc.value.path == str(path) and "quick_check" in exc.value.cause
    assert str(exc.value).startswith(f"{path}: database is corrupt (")
    assert "\n" not in str(exc.value) and "*** in database" not in str(exc.value)
    assert isinstance(exc.value, StorageError) and exc.value.transient  # never the work's


def test_a_file_that_is_not_a_database_is_corrupt_even_without_the_check(tmp_path):
    path = tmp_path / "junk.sqlite"
    path.write_bytes(b"\xa5" * 3 * PAGE)
    with pytest.raises(DatabaseCorrupt, match=r"junk\.sqlite: database is corrupt \(file is not"):
        connect(path)


def test_a_transaction_that_meets_damage_raises_database_corrupt(tmp_path):
    path = filled(tmp_path / "a.sqlite")
    db = connect(path, check=True)
    other = connect(path)
    other.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    overwrite(path, pages_of(path, "seen"))
    other.execute("INSERT INTO other(body) VALUES (x'00')")  # db re-reads the file
    other.close()
    with pytest.raises(DatabaseCorrupt) as exc, transaction(db):
        db.execute("INSERT INTO seen VALUES ('veh', 99999)")
    assert exc.value.path == str(path) and "malformed" in exc.value.cause
    db.close()


def test_a_locked_database_is_not_reported_as_corrupt(tmp_path):
    path = filled(tmp_path / "a.sqlite")
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("PRAGMA journal_mode=DELETE")
    holder.execute("BEGIN EXCLUSIVE")
    try:
        db = sqlite3.connect(path, isolation_level=None, timeout=0)
        with pytest.raises(sqlite3.OperationalError, match="locked"):
            check_integrity(db, path)
        db.close()
    finally:
        holder.execute("ROLLBACK")
        holder.close()


class Bare(Service):
    name = "bare"


def test_a_service_on_a_corrupt_database_stops_with_its_exit_code(tmp_path, caplog):
    opts = ServiceOptions(data_dir=tmp_path)
    Bare(opts).db.close()
    path = tmp_path / "bare-all" / "state.sqlite"
    filled_pages = pages_of(path, "counters")
    overwrite(path, filled_pages)
    with caplog.at_level(logging.ERROR), pytest.raises(PermanentFault) as exc:
        Bare(opts)
    assert exc.value.code == EXIT_CORRUPT and isinstance(exc.value, SystemExit)
    assert exc.value.fault.path == str(path)
    [line] = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert line.startswith(f"bare: {path}: database is corrupt (") and "\n" not in line


# -- UploadAck.permanent ---------------------------------------------------------------------


def test_permanent_round_trips_and_defaults_to_false():
    err = DecodeError("storage", "not recorded: ingest's database is corrupt")
    ack = UploadAck("veh-1", 0, np.zeros(0, np.uint64), error=err, retry_after_s=300.0)
    assert not UploadAck.from_bytes(ack.to_bytes()).permanent
    perm = UploadAck("veh-1", 0, ack.accepted, error=err, retry_after_s=300.0, permanent=True)
    back = UploadAck.from_bytes(perm.to_bytes())
    assert back.permanent and back.retry_after_s == 300.0 and back.error.field == "storage"


def _with(ack: UploadAck, **changes: object) -> bytes:
    m = msgpack.unpackb(ack.to_bytes())
    for k, v in changes.items():
        if v is None:
            m.pop(k)
        else:
            m[k] = v
    return msgpack.packb(m)


def test_the_field_is_sent_only_when_true_as_an_older_ingest_speaks():
    err = DecodeError("storage", "not recorded, retry later")
    ack = UploadAck("veh-1", 0, np.zeros(0, np.uint64), error=err, retry_after_s=5.0)
    assert "permanent" not in msgpack.unpackb(ack.to_bytes())
    assert not UploadAck.from_bytes(_with(ack, permanent=False)).permanent
    perm = UploadAck("veh-1", 0, ack.accepted, error=err, permanent=True)
    assert not UploadAck.from_bytes(_with(perm, permanent=None)).permanent


def test_a_bad_permanent_field_is_refused():
    err = DecodeError("storage", "x")
    ack = UploadAck("veh-1", 0, np.zeros(0, np.uint64), error=err)
    with pytest.raises(DecodeError, match="permanent"):
        UploadAck.from_bytes(_with(ack, permanent=1))
    ok = UploadAck("veh-1", 0, np.zeros(0, np.uint64))
    with pytest.raises(DecodeError, match="permanent"):
        UploadAck.from_bytes(_with(ok, permanent=True))  # permanent, but nothing refused


# -- the vehicle backs off on a permanent refusal ----------------------------------------


def test_the_uploader_keeps_its_queue_and_backs_off_on_permanent_refusals(tmp_path, monkeypatch):
    clock = Clock()
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=10, clock=clock)
    up.enqueue(1, make_observations(15))
    sent: list[ObservationBatch] = []
    broken = [True]

    def send(_session, batch: ObservationBatch, _timeout: float) -> UploadAck:
        sent.append(batch)
        ids = batch.obs.obs_id
        if broken[0]:
            err = DecodeError("storage", "not recorded: ingest's database is corrupt (...)")
            return UploadAck("veh-1", 0, ids[:0], error=err, retry_after_s=5.0, permanent=True)
        return UploadAck("veh-1", batch.batch_id, ids)

    monkeypatch.setattr(up, "_send", send)
    waits = []
    for _ in range(8):
        res = up.flush(None)
        assert res.failed_batches == 1 and "corrupt" in res.permanent_fault
        waits.append(res.retry_after_s)
        clock.t += res.retry_after_s / 2
        held = up.flush(None)  # halfway: nothing is sent, the reason is still given
        assert held.sent == 0 and "corrupt" in held.permanent_fault
        clock.t += res.retry_after_s / 2
    assert waits[0] == PERMANENT_BACKOFF_MIN_S  # not the 5 s the ack asked for
    assert waits == sorted(waits) and waits[-1] == PERMANENT_BACKOFF_MAX_S
    assert len(sent) == 8 and up.pending == 15 and up.rejected() == []

    broken[0] = False  # the operator restored ingest's database
    res = up.flush(None)
    assert res.accepted == 15 and up.pending == 0 and res.permanent_fault == ""
    assert up.fault == "" and up.retry_in == 0.0
    up.close()
