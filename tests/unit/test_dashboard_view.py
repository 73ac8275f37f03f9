"""The dashboard's memory (:mod:`hdmap.ops.dashboard.view`): what changed between two
maps, and each landmark's bounded history."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hdmap.ops.dashboard.view import MapView, latest_per_id
from schemas.map import MapLandmarks


def rows(ids, revisions, passes=None) -> MapLandmarks:
    n = len(ids)
    lm = MapLandmarks.empty()
    cols = {
        "id": np.asarray(ids, np.uint64),
        "sign_class": np.full(n, 3, np.uint16),
        "lat": np.full(n, 60.0) + np.arange(n) * 1e-4,
        "lon": np.full(n, 25.0),
        "h": np.zeros(n),
        "cov": np.tile([1.0, 0.0, 0.0, 1.0, 0.0, 1.0], (n, 1)),
        "status": np.ones(n, np.uint8),
        "n_obs": np.full(n, 10, np.uint32),
        "n_passes": np.asarray(passes if passes is not None else [2] * n, np.uint32),
        "revision": np.asarray(revisions, np.uint64),
        "updated_at": np.full(n, 1.0),
        "source_time": np.full(n, 1.0),
        "facing_deg": np.full(n, 90.0, np.float32),
        "facing_sigma_deg": np.full(n, 2.0, np.float32),
        "exist_state": np.ones(n, np.uint8),
        "p_exist": np.full(n, 0.9, np.float32),
        "first_seen": np.ones(n),
        "last_seen": np.ones(n),
    }
    return replace(lm, **cols)


def test_changes_and_history():
    v = MapView(history_len=3)
    c = v.update(rows([1, 2], [1, 1]), now=10.0)
    assert {f["properties"]["id"] for f in c.upserts} == {"1", "2"} and c.removed == []
    assert len(c.upserts) == 6  # point, ellipse, arrow each
    assert not v.update(rows([1, 2], [1, 1]), now=11.0)  # same revisions: nothing
    c = v.update(rows([1, 2, 3], [2, 1, 1], passes=[4, 2, 2]), now=12.0)
    assert sorted({f["properties"]["id"] for f in c.upserts}) == ["1", "3"]
    c = v.update(rows([1, 3], [2, 1], passes=[4, 2]), now=13.0)
    assert c.upserts == [] and c.removed == ["2"]
    h1 = v.history("1")
    assert [(e["seen_at"], e["revision"], e["passes"]) for e in h1] == [(10.0, 1, 2), (12.0, 2, 4)]
    assert v.history("2")[-1] == {"seen_at": 13.0, "revision": 1, "removed": True}
    assert v.history("99") is None
    assert v.counts()["confirmed"] == 2 and len(v) == 2
    assert len(v.collection()["features"]) == 6
    for t in range(5):  # bounded per landmark
        v.update(rows([1, 3], [10 + t, 1]), now=20.0 + t)
    assert [e["revision"] for e in v.history("1")] == [12, 13, 14]


def test_history_is_bounded_in_landmarks():
    v = MapView(history_landmarks=2)
    for i in range(1, 5):
        v.update(rows([i], [1]), now=float(i))
    assert v.history("1") is None and v.history("2") is None
    assert v.history("3") is not None and v.history("4") is not None


def test_a_landmark_in_two_tiles_counts_once_at_its_latest_revision():
    lm = MapLandmarks.concat([rows([5, 7], [3, 1]), rows([5], [4])])
    latest = latest_per_id(lm)
    assert dict(zip(latest.id.tolist(), latest.revision.tolist(), strict=True)) == {5: 4, 7: 1}
