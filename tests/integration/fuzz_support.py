"""Shared by the service-endpoint fuzz tests (test_fuzz_endpoints, test_fuzz_internal).

They run over a real stack (router + the four services as processes) while an honest
vehicle uploads *during* the fuzz; afterwards every process must be alive, have its
liveliness token and answer stats, and the honest vehicle must have had every upload
acknowledged and applied by the matcher. This module holds those checks, the honest
vehicle, the ``live`` fixture, and ``rejected_delta``
(what a service counted in ``Stats.rejected``, by reason, between two stats).
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections import Counter
from collections.abc import Iterator

import pytest
import zenoh

from hdmap.ops.stack import SERVICE_NAMES, Stack, tail
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from hdmap.runtime.store import connect
from schemas import DecodeError, LogEntry, ObservationBatch, ObsGroup, Stats, UploadAck, keys
from tests.support import wait_until
from tests.support.hostile import observations

# --- the stack --------------------------------------------------------------------------------


def stats_by_service(session) -> dict[str, Stats]:
    return {s.service: s for s in collect(session)}


def assert_all_alive(stack: Stack, session) -> dict[str, Stats]:
    """Every process runs, has its liveliness token and answers stats."""
    for name, p in stack.procs.items():
        assert p.alive, f"{name} died:\n{tail(p.log_path)}"
    alive = {
        str(r.ok.key_expr).split("/")[3]
        for r in session.liveliness().get(f"{keys.ROOT}/alive/**", timeout=5.0)
        if r.ok
    }
    assert alive == set(SERVICE_NAMES)
    stats = stats_by_service(session)
    assert set(stats) == set(SERVICE_NAMES), stats.keys()
    return stats


def read_db(stack: Stack, service: str, sql: str) -> list[tuple]:
    conn = connect(stack.data_dir / f"{service}-all" / "state.sqlite", readonly=True)
    try:
        return conn.execute(sql).fetchall()
    except sqlite3.OperationalError:  # the table does not exist yet
        return []
    finally:
        conn.close()


class HonestVehicle(threading.Thread):
    """Uploads a small valid batch every ``period`` s while the fuzz runs; keeps every ack
    and, from the obs stage, the log entries its observations went out in."""

    def __init__(self, stack: Stack, vehicle: str = "honest-1", period: float = 0.15):
        super().__init__(name=vehicle, daemon=True)
        self.stack, self.vehicle, self.period = stack, vehicle, period
        self.stop = threading.Event()
        self.acks: list[UploadAck] = []
        self.failures: list[str] = []
        self.sent_ids: set[int] = set()
        self.entries: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()

    def _on_entry(self, sample: zenoh.Sample) -> None:
        try:
            e = LogEntry.from_bytes(sample.payload.to_bytes())
            g = ObsGroup.from_bytes(e.body)
        except DecodeError:
            return
        if g.vehicle_id == self.vehicle:
            with self._lock:
                k = (e.producer, e.tile)
                self.entries[k] = max(self.entries.get(k, 0), e.seq)

    def run(self) -> None:
        with open_session(self.stack.bus) as s:
            sub = s.declare_subscriber(keys.obs("*"), self._on_entry)
            try:
                for batch_id in range(1, 2000):
                    if self.stop.wait(self.period if batch_id > 1 else 0.0):
                        break
                    obs = observations(8, seed=batch_id, lat=60.2, lon=24.9)
                    now = time.time()
                    batch = ObservationBatch(self.vehicle, batch_id, batch_id, now, obs)
                    payload = batch.to_bytes()
                    replies = query(s, keys.upload(self.vehicle), payload, timeout=20.0)
                    oks = [ok for _k, ok, _e in replies if ok is not None]
                    if len(oks) != 1:
                        self.failures.append(f"batch {batch_id}: replies {replies}")
                        continue
                    self.acks.append(UploadAck.from_bytes(oks[0]))
                    self.sent_ids.update(int(i) for i in obs.obs_id)
            except Exception as exc:  # noqa: BLE001 - reported by check(), not lost in the thread
                self.failures.append(repr(exc))
            finally:
                time.sleep(0.3)  # the last entries' live samples
                sub.undeclare()

    def finish(self) -> None:
        self.stop.set()
        self.join(30)
        assert not self.is_alive()

    def check(self, stack: Stack) -> None:
        """Every upload acknowledged in full, and applied by the matcher."""
        assert not self.failures, self.failures[:5]
        assert len(self.acks) >= 3, f"only {len(self.acks)} honest uploads during the fuzz"
        for a in self.acks:
            assert a.error is None and not a.rejected, a
        accepted = {int(i) for a in self.acks for i in a.accepted}
        assert accepted == self.sent_ids
        assert self.entries, "no obs entry of the honest vehicle was published"

        def applied() -> bool:
            done = dict(
                ((p, t), s)
                for p, t, s in read_db(stack, "matcher", "SELECT producer, tile, seq FROM offsets")
            )
            return all(done.get(k, 0) >= s for k, s in self.entries.items())

        assert wait_until(applied, timeout=60.0), "the matcher did not apply the honest uploads"


@pytest.fixture
def live(stack: Stack) -> Iterator[tuple[Stack, zenoh.Session, HonestVehicle]]:
    """The whole stack, a client session and an honest vehicle uploading meanwhile (the
    fuzz modules' fixture: tests/integration/conftest.py makes it theirs)."""
    stack.start_all()
    with open_session(stack.bus) as s:
        honest = HonestVehicle(stack)
        honest.start()
        try:
            yield stack, s, honest
        finally:
            honest.stop.set()
            honest.join(30)


def rejected_delta(before: Stats, after: Stats) -> Counter:
    """What a service counted in ``Stats.rejected`` since ``before``, by reason."""
    d = Counter(after.rejected)
    d.subtract(before.rejected)
    return +d
