"""Two ingest instances, vehicles sharded by id (issue 20, ingest scale-out): router,
two ingests (``--shard 0/2``, ``--shard 1/2``), matcher, solver and publisher as
processes on 127.0.0.1.

Each upload gets exactly one answer (from its vehicle's shard; the other instance drops
the query unanswered), every vehicle always reaches the same instance, so its dedup
table sees all its retries: each upload is sent twice and the second answer names every
observation a duplicate. Both instances take uploads; the matcher receives every
acknowledged observation once, from both producers' logs.
"""

from __future__ import annotations

import numpy as np
import pytest

from fleetsim.synthetic import make_observations
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import SERVICE_NAMES
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from hdmap.runtime.shards import shard_of
from tests.support.uploads import upload
from vehicle.uploader import Uploader

pytestmark = pytest.mark.integration

VEHICLES = [f"veh-{i:04d}" for i in range(1, 9)]
UPLOADS = 5
N = 15


def test_two_ingests_shard_the_vehicles_and_keep_exactly_once(stack, tmp_path):
    assert {shard_of(v, 2) for v in VEHICLES} == {0, 1}  # both shards have vehicles
    stack.start_router()
    for name in SERVICE_NAMES:
        if name == "ingest":
            stack.start_service(name, shard=(0, 2))
            stack.start_service(name, shard=(1, 2))
        else:
            stack.start_service(name)
    stack.wait_ready(["ingest-all-s0of2", "ingest-all-s1of2", "matcher-all", "solver-all"])
    with open_session(stack.bus) as s:
        acked = 0
        for k in range(UPLOADS):
            for j, v in enumerate(VEHICLES):
                first = (j * UPLOADS + k) * N
                ack = upload(s, v, k + 1, first, N)  # exactly one answer (asserted)
                assert len(ack.accepted) == N and len(ack.duplicates) == 0, ack
                again = upload(s, v, k + 1, first, N)  # a retry after a lost answer
                assert len(again.duplicates) == N and len(again.accepted) == N, again
                acked += N
        # the vehicle SDK's uploader (the whole queue, retries and all) gets its answers too
        for j, v in enumerate(VEHICLES):
            up = Uploader(v, tmp_path / f"{v}.sqlite", batch_size=10)
            obs = make_observations(N, seed=j)
            obs.obs_id[:] = np.arange(10_000 + j * N, 10_000 + (j + 1) * N, dtype=np.uint64)
            up.enqueue(99, obs)
            res = up.flush(s, timeout=10.0)
            assert res.failed_batches == 0 and up.pending == 0, (v, res)
            up.close()
            acked += N
        assert wait_quiet(s, 60.0)
        per = {x.instance: x.counters for x in collect(s, 2.0) if x.service == "ingest"}
        assert len(per) == 2
        assert all(c["uploads"] > 0 for c in per.values())  # both took their vehicles'
        assert sum(c["duplicates"] for c in per.values()) == UPLOADS * len(VEHICLES) * N
        t = totals(collect(s, 2.0))
        assert t["ingest"]["log_entries"] == t["matcher"]["entries_applied"]
        assert t["matcher"]["received"] == acked
        assert sorted(p.name for p in stack.data_dir.iterdir() if p.name.startswith("ingest")) == [
            "ingest-all-s0of2",
            "ingest-all-s1of2",
        ]
