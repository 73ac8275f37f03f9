"""Ingest takes a pass's absences (issue 21: mapped landmarks the pass had in view and did
not detect) with its observations: validated row by row (a bad row refused naming its
column, the rest kept), admitted in the observations' time window, recorded once per
(vehicle, pass, landmark), routed to each landmark's home tile, acknowledged with a count.
In-process ingest on real SQLite, its wall clock injected."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fleetsim.synthetic import make_observations
from hdmap.geo.tiles import quadkeys_of
from hdmap.runtime.service import Item, ServiceOptions
from schemas import Absences, ObservationBatch, Observations, ObsGroup, UploadAck, keys
from schemas.ids import home_tile, landmark_id
from services.ingest.admission import AdmissionPolicy
from services.ingest.service import IngestConfig, IngestService

NOW = 1.8e9
HOUR = 3600.0


def absences(ids, t=NOW - 60.0, **cols) -> Absences:
    n = len(ids)
    base = {
        "landmark_id": np.asarray(ids, np.uint64),
        "t": np.full(n, t),
        "frames": np.full(n, 12, np.uint32),
        "share": np.full(n, 0.3, np.float32),
        "range_m": np.full(n, 18.0, np.float32),
        "bearing_deg": np.full(n, 10.0, np.float32),
    }
    base.update(cols)
    return Absences(**base)


@pytest.fixture
def svc(tmp_path: Path):
    s = IngestService(
        ServiceOptions(data_dir=tmp_path),
        IngestConfig(policy=AdmissionPolicy(max_age_s=10 * HOUR)),
    )
    s.wall = lambda: NOW
    yield s
    s.db.close()


def send(svc: IngestService, obs: Observations, ab: Absences, pass_id: int = 1, batch: int = 1):
    data = ObservationBatch("veh-1", pass_id, batch, NOW, obs, ab).to_bytes()
    with svc.transaction(svc.participants):
        ack, entries = svc._stage(Item("upload", keys.upload("veh-1"), data))
    ack = UploadAck.from_bytes(ack.to_bytes())  # what the vehicle reads
    return ack, [(e.tile, ObsGroup.from_bytes(e.body)) for e in entries]


def two_homes(svc) -> tuple[list[int], list[str]]:
    """Landmark ids in two home tiles: the observations' tile and another one."""
    here = str(quadkeys_of(np.array([60.17]), np.array([24.94]), svc.opts.zoom)[0])
    there = str(quadkeys_of(np.array([61.0]), np.array([25.5]), svc.opts.zoom)[0])
    return [landmark_id(here, 3), landmark_id(here, 4), landmark_id(there, 9)], [here, there]


def test_absences_go_to_their_landmarks_home_tiles_once(svc):
    ids, (here, there) = two_homes(svc)
    obs = make_observations(5, t=NOW - 60.0)
    ack, groups = send(svc, obs, absences(ids))
    assert ack.error is None and ack.absences == 3 and len(ack.accepted) == 5
    got = {tile: g.absences.landmark_id.tolist() for tile, g in groups if len(g.absences)}
    assert got == {here: ids[:2], there: ids[2:]}
    assert all(home_tile(i, svc.opts.zoom) == t for t, lst in got.items() for i in lst)
    only_absence = [g for t, g in groups if t == there]
    assert len(only_absence) == 1 and len(only_absence[0].obs) == 0

    again, groups = send(svc, Observations.empty(), absences(ids), batch=2)  # a resend
    assert again.absences == 3 and groups == []  # acknowledged, not logged twice
    assert svc.counters["absences_accepted"] == 3 and svc.counters["absences_duplicates"] == 3
    other_pass, groups = send(svc, Observations.empty(), absences(ids[:1]), pass_id=2)
    assert other_pass.absences == 1 and [g.absences.landmark_id.tolist() for _, g in groups] == [
        ids[:1]
    ]


def test_bad_absence_rows_are_refused_by_column_and_the_rest_kept(svc):
    ids, _ = two_homes(svc)
    ab = absences(
        [*ids, ids[0]],
        share=np.array([0.3, 1.5, 0.3, 0.3], np.float32),
        t=np.array([NOW - 60.0, NOW - 60.0, np.nan, NOW - 60.0]),
    )
    ack, groups = send(svc, make_observations(3, t=NOW - 60.0), ab)
    by_field = {(r.field, r.obs_id) for r in ack.rejected}
    assert by_field == {
        ("absences.share", ids[1]),
        ("absences.t", ids[2]),
        ("absences.landmark_id", ids[0]),  # reported twice in one batch
    }
    assert ack.absences == 1 and len(ack.accepted) == 3
    logged = [i for _, g in groups for i in g.absences.landmark_id.tolist()]
    assert logged == [ids[0]]
    assert svc.rejected["absences.share"] == 1 and svc.rejected["absences.landmark_id"] == 1


def test_absences_outside_the_time_window_are_refused_and_forgotten_later(svc):
    ids, _ = two_homes(svc)
    ack, _ = send(svc, Observations.empty(), absences(ids[:1], t=NOW - 11 * HOUR))
    assert ack.absences == 0 and [r.field for r in ack.rejected] == ["absences.t"]
    ack, _ = send(svc, Observations.empty(), absences(ids[1:2], t=NOW + 3600.0))
    assert [r.field for r in ack.rejected] == ["absences.t"]
    ack, _ = send(svc, Observations.empty(), absences(ids[2:], t=NOW - 9 * HOUR))
    assert ack.absences == 1
    svc.wall = lambda: NOW + 2 * HOUR
    assert svc.prune_seen() == 1
    assert svc.db.execute("SELECT COUNT(*) FROM seen_absence").fetchone()[0] == 0
