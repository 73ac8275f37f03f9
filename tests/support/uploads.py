"""One upload by request/reply, as a vehicle sends it, for tests against a live ingest."""

from __future__ import annotations

import time

import numpy as np

from fleetsim.synthetic import make_observations
from hdmap.runtime.bus import query
from schemas import ObservationBatch, UploadAck, keys


def upload(s, vehicle: str, batch_id: int, first: int, n: int) -> UploadAck:
    """``n`` observations with ids ``first ..`` in pass 1; ingest's one ack."""
    obs = make_observations(n, seed=batch_id)
    obs.obs_id[:] = np.arange(first, first + n, dtype=np.uint64)
    payload = ObservationBatch(vehicle, 1, batch_id, time.time(), obs).to_bytes()
    replies = [ok for _k, ok, _e in query(s, keys.upload(vehicle), payload, 10.0) if ok]
    assert len(replies) == 1
    return UploadAck.from_bytes(replies[0])
