"""Ingest's dedup table keeps only ids inside the admission window (issue 20, bounded
storage): an id whose capture time is past ``max_age_s`` (and a minute) is forgotten, and
sending it again is refused as too old, never recorded twice; ids inside the window are
still known. In-process ingest on real SQLite, its wall clock injected."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np

from fleetsim.synthetic import make_observations
from hdmap.runtime.service import Item, ServiceOptions
from schemas import ObservationBatch, keys
from services.ingest.admission import AdmissionPolicy
from services.ingest.service import IngestConfig, IngestService

NOW = 1.8e9
HOUR = 3600.0


def send(svc: IngestService, first: int, t: float, n: int = 10):
    obs = make_observations(n, t=t)
    obs.obs_id[:] = np.arange(first, first + n, dtype=np.uint64)
    data = ObservationBatch("veh-1", 1, first, t, obs).to_bytes()
    with svc.transaction(svc.participants):
        ack, _entries = svc._stage(Item("upload", keys.upload("veh-1"), data))
    return ack


def test_ids_past_the_admission_window_are_forgotten_and_cannot_come_back(tmp_path: Path):
    svc = IngestService(
        ServiceOptions(data_dir=tmp_path),
        IngestConfig(policy=AdmissionPolicy(max_age_s=10 * HOUR)),
    )
    try:
        svc.wall = lambda: NOW
        old = send(svc, 1, NOW - 9 * HOUR)  # inside the window when it arrives
        recent = send(svc, 100, NOW - 1 * HOUR)
        assert len(old.accepted) == 10 and len(recent.accepted) == 10
        assert svc.prune_seen() == 0  # nothing past the window yet

        svc.wall = lambda: NOW + 2 * HOUR  # the old ones are now 11 h old
        assert svc.prune_seen() == 10 and svc.counters["seen_pruned"] == 10
        rows = svc.db.execute("SELECT COUNT(*) FROM seen").fetchone()[0]
        assert rows == 10
        again = send(svc, 1, NOW - 9 * HOUR)  # a late retry of the forgotten ones
        assert len(again.accepted) == 0 and {r.field for r in again.rejected} == {"obs.t"}
        assert len(send(svc, 100, NOW - 1 * HOUR).duplicates) == 10  # still known
        assert svc.counters["accepted"] == 20
    finally:
        svc.db.close()


def test_a_dedup_table_from_before_times_keeps_its_ids_one_window(tmp_path: Path):
    db = tmp_path / "ingest-all" / "state.sqlite"
    db.parent.mkdir(parents=True)
    conn = sqlite3.connect(db)
    conn.execute(
        "CREATE TABLE seen (vehicle TEXT NOT NULL, obs_id INTEGER NOT NULL, "
        "PRIMARY KEY (vehicle, obs_id)) WITHOUT ROWID"
    )
    conn.execute("INSERT INTO seen VALUES ('veh-1', 5)")
    conn.commit()
    conn.close()
    svc = IngestService(ServiceOptions(data_dir=tmp_path))
    try:
        assert svc.prune_seen() == 0  # the upgrade time stands for its capture time
        (t,) = svc.db.execute("SELECT t FROM seen").fetchone()
        assert t > NOW - 1e8
    finally:
        svc.db.close()


def test_with_a_lag_the_table_follows_the_fleets_own_clock(tmp_path: Path):
    """An accelerated stream (a replay, a soak): capture times run ahead of the wall
    clock, well inside the 30-day age window. ``max_lag_s`` refuses what is more than an
    hour behind the newest observation admitted, so ids older than that are forgotten
    while the wall clock stands still; the newest capture time survives a restart."""
    pol = AdmissionPolicy(max_lag_s=HOUR)
    svc = IngestService(ServiceOptions(data_dir=tmp_path), IngestConfig(policy=pol))
    t0 = NOW - 20 * 24 * HOUR
    try:
        svc.wall = lambda: NOW
        for k in range(3):  # two hours of the fleet's time between uploads
            assert len(send(svc, 100 * k, t0 + 2 * k * HOUR).accepted) == 10
        assert svc.horizon == t0 + 4 * HOUR
        assert svc.prune_seen() == 20  # the first two uploads' ids
        late = send(svc, 0, t0)  # sent again: refused, not recorded twice
        assert len(late.accepted) == 0 and {r.field for r in late.rejected} == {"obs.t"}
        assert "newest observation" in late.rejected[0].reason
        assert len(send(svc, 200, t0 + 4 * HOUR).duplicates) == 10
    finally:
        svc.db.close()
    again = IngestService(ServiceOptions(data_dir=tmp_path), IngestConfig(policy=pol))
    try:
        assert again.horizon == t0 + 4 * HOUR
    finally:
        again.db.close()
