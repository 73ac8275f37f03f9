"""What a vehicle's ``upload()`` says about refused observations: counts by the field ingest
named, one log line per field and batch, the batch refusal itself, and the rows kept."""

from __future__ import annotations

import itertools
import logging

from fleetsim.synthetic import make_observations
from schemas import DecodeError, ObservationBatch, Rejection, UploadAck
from tests.support import Clock
from vehicle.uploader import Uploader


def test_refused_rows_are_counted_by_field_and_logged(tmp_path, monkeypatch, caplog):
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=10, clock=Clock())
    obs = make_observations(20, seed=1)
    up.enqueue(1, obs)
    calls = []

    def send(_session, batch: ObservationBatch, _timeout: float) -> UploadAck:
        calls.append(batch)
        ids = batch.obs.obs_id
        if len(calls) == 3:
            err = DecodeError("vehicle.new", "vehicle 'veh-1' is new; retry after 2 s")
            return UploadAck("veh-1", batch.batch_id, ids[:0], error=err, retry_after_s=2.0)
        bad = [Rejection(int(i), "obs.lat", "latitude 91 outside [-90, 90]") for i in ids[:2]]
        bad.append(Rejection(int(ids[2]), "obs.t", "captured 400 s in the future"))
        return UploadAck("veh-1", batch.batch_id, ids[3:], rejected=bad)

    monkeypatch.setattr(up, "_send", send)
    with caplog.at_level(logging.WARNING, logger="vehicle.uploader"):
        res = up.flush(None)
    assert (res.accepted, res.rejected) == (14, 6)
    assert res.rejected_by == {"obs.lat": 4, "obs.t": 2}
    assert res.refused == "" and res.failed_batches == 0
    lines = [r.getMessage() for r in caplog.records]
    assert sum("on obs.lat: latitude 91" in ln for ln in lines) == 2  # one per batch
    assert sum("on obs.t: captured" in ln for ln in lines) == 2
    assert sorted(r.field for r in up.rejected()) == ["obs.lat"] * 4 + ["obs.t"] * 2

    up.enqueue(2, make_observations(5, seed=2))
    res = up.flush(None)
    assert res.refused.startswith("vehicle.new: ") and res.retry_after_s == 2.0
    assert res.failed_batches == 1 and up.pending == 5
    up.close()


def rate_limited(refuse):
    """A stand-in for ``Uploader._send``: each batch refused for its rate (retry after
    0.1 s) or accepted whole, as ``refuse`` (an iterator of booleans) says."""

    def send(_session, batch: ObservationBatch, _timeout: float) -> UploadAck:
        if next(refuse):
            err = DecodeError("rate", "vehicle 'veh-1' sends too much; retry after 0.1 s")
            return UploadAck("veh-1", batch.batch_id, batch.obs.obs_id[:0], error=err,
                             retry_after_s=0.1)  # fmt: skip
        return UploadAck("veh-1", batch.batch_id, batch.obs.obs_id)

    return send


def test_a_refusal_streak_warns_once_and_says_when_it_ends(tmp_path, monkeypatch, caplog):
    """A bulk upload paced by the rate limit is refused once per batch; each retry would
    say the same, so the streak warns once and ends with one line."""
    clock = Clock()
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=5, clock=clock)
    up.enqueue(1, make_observations(10, seed=3))
    monkeypatch.setattr(up, "_send", rate_limited(iter([True, True, True, False, False])))
    with caplog.at_level(logging.DEBUG, logger="vehicle.uploader"):
        for _ in range(5):
            res = up.flush(None)
            clock.t += 0.2
    assert up.pending == 0 and res.refused == ""
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "batch refused: rate" in warned[0].getMessage()
    assert sum("batch refused" in r.getMessage() for r in caplog.records) == 3
    assert any("accepted again after 3 refused" in r.getMessage() for r in caplog.records)
    up.close()


def test_refusals_paced_by_the_rate_limit_warn_once_a_minute(tmp_path, monkeypatch, caplog):
    """A bulk upload the rate limit paces is refused every other batch: streaks of one.
    One warning a minute, the next one counting the refusals in between."""
    clock = Clock()
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=1, clock=clock)
    up.enqueue(1, make_observations(40, seed=4))
    monkeypatch.setattr(up, "_send", rate_limited(itertools.cycle([True, False])))
    with caplog.at_level(logging.DEBUG, logger="vehicle.uploader"):
        for _ in range(40):  # 20 refusals within 8 s
            up.flush(None, max_batches=1)
            clock.t += 0.2
        clock.t += 60.0
        while up.pending:
            up.flush(None, max_batches=1)
            clock.t += 0.2
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 2 and all("batch refused: rate" in w for w in warned)
    assert "more batch(es) refused since the last warning" in warned[1]
    up.close()
