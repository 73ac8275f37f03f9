"""A region's matcher and solver state cut into sub-regions and joined again
(:mod:`hdmap.runtime.partition`, the rules in ``services/*/partition.py``): each part
holds its region's landmarks, pending rays and offsets, and goes on exactly as the whole
would have. Two towns in different quadrants of the world (Helsinki, quadkey 1...; and the
same streets at 60 S, 3...), passes of four vehicles at two signs each; the whole state
after the first half of the log, cut, and the second half fed to the parts by tile, gives
the landmarks (packed sums, bytes) the whole gets from the whole log; joined back, the
same."""

from __future__ import annotations

import sqlite3
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hdmap.geo.tiles import quadkeys_of, region_label
from hdmap.runtime.partition import merge, split
from hdmap.runtime.service import ServiceOptions
from schemas import LandmarkUpdates, LogEntry, ObsGroup
from services.matcher.partition import RULES as MATCHER
from services.matcher.replay import (
    Sink,
    landmark_digest,
    matcher_config,
    open_matcher,
    read_log,
    replay,
)
from services.matcher.service import MatcherService
from services.solver.partition import RULES as SOLVER
from services.solver.service import SolverService
from tests.support.services import SIGN, sign_rays

T0 = 1.7e9
TOWNS = {"1": (60.17, 24.94), "3": (-60.17, 24.94)}  # quadrant -> (lat, lon)
OTHER = SIGN + np.array([-8.0, 6.0, 0.0])
PARTS = (["1"], ["0", "2", "3"])


def tile(quadrant: str, zoom: int) -> str:
    lat, lon = TOWNS[quadrant]
    return str(quadkeys_of(np.array([lat]), np.array([lon]), zoom)[0])


LATE = SIGN + np.array([-20.0, 30.0, 0.0])
"""A sign put up during the log: town 1's passes from the 25th on see it (``late``)."""


def traffic(m: MatcherService, late: bool = False) -> list[LogEntry]:
    """40 passes alternating between the towns, vehicles 0-1 in one, 2-3 in the other;
    each pass also sees a stray sign no other pass does (its rays stay pending); with
    ``late``, town 1's passes from the 25th on also see the sign :data:`LATE`."""
    out = []
    for k in range(40):
        q = "1" if k % 2 == 0 else "3"
        t = tile(q, m.opts.zoom)
        frame = m.frames(t)
        rng = np.random.default_rng(k)
        obs = sign_rays(frame, k + 1, rng)
        o2 = sign_rays(frame, k + 1, rng, at=OTHER, image0=50)
        o2 = replace(o2, obs_id=o2.obs_id + 500, sign_class=o2.sign_class + 1)
        stray = SIGN + np.array([40.0, -20.0 + 7.0 * (k % 6), 0.0])  # one pass each: pending
        o3 = sign_rays(frame, k + 1, rng, n=3, at=stray, image0=80)
        o3 = replace(o3, obs_id=o3.obs_id + 800, sign_class=o3.sign_class + 5)
        parts = [obs, o2, o3]
        if late and q == "1" and k >= 24:
            o4 = sign_rays(frame, k + 1, rng, at=LATE, image0=110)
            parts.append(replace(o4, obs_id=o4.obs_id + 1200, sign_class=o4.sign_class + 2))
        obs = type(obs).concat(parts)
        at = T0 + 5.0 * k
        obs = replace(obs, t=at - np.linspace(2.0, 0.0, len(obs)))
        vehicle = f"veh-{(k // 2) % 2 + (0 if q == '1' else 2)}"
        body = ObsGroup(vehicle, k + 1, k + 1, at + 1.0, obs).to_bytes()
        out.append(LogEntry("obs", "ingest-t", t, k // 2 + 1, k + 1, body))
    return out


def landmarks(svc) -> dict[int, bytes]:
    """Every landmark's packed sums (the bytes) by id."""
    lms = svc.state.landmarks
    ids = sorted(lms)
    return dict(zip(ids, svc.sums.pack_rows(np.array([lms[i].row for i in ids])), strict=True))


def checkpoint(svc, path: Path) -> Path:
    """What a paused instance hands out: ``before_handover`` then a copy of its database."""
    with svc.transaction(svc.participants()):
        svc.before_handover()
    dst = sqlite3.connect(path)
    svc.db.backup(dst)
    dst.close()
    return path


def published(entries: list[LogEntry]) -> dict[int, tuple]:
    """The map a solver's update entries leave (each landmark's last row, less removals):
    id -> (tile, lat, lon, h, cov, status, n_obs, n_passes)."""
    out: dict[int, tuple] = {}
    for e in entries:
        u = LandmarkUpdates.from_bytes(e.body)
        lm = u.landmarks
        for k, i in enumerate(lm.id.tolist()):
            out[i] = (e.tile, *(np.asarray(getattr(lm, c)[k]).tolist() for c in ROW))
        for i in u.removed.id.tolist():
            out.pop(i, None)
    return out


ROW = ("lat", "lon", "h", "cov", "status", "n_obs", "n_passes")


def in_part(e: LogEntry, part: list[str]) -> bool:
    return any(e.tile.startswith(p) for p in part)


@pytest.fixture
def logs(tmp_path: Path):
    m = open_matcher(tmp_path / "gen")
    entries = traffic(m)
    m.db.close()
    return entries


def open_part(cls, root: Path, part: list[str]):
    """A service of region ``part`` on ``root`` (its data dir named for the region)."""
    svc = cls(ServiceOptions(data_dir=root, region=tuple(part)))
    svc.pubs = Sink(keep=True)  # type: ignore[assignment]
    return svc


def db_of(cls, root: Path, part: list[str]) -> Path:
    return root / f"{cls.name}-{region_label(part)}" / "state.sqlite"


def test_a_matcher_cut_in_two_goes_on_as_the_whole_and_joins_back(tmp_path, logs) -> None:
    half = len(logs) // 2
    whole = open_matcher(tmp_path / "whole")
    replay(whole, logs[:half], 4)
    cp = checkpoint(whole, tmp_path / "m.sqlite")
    pending = whole.state.pending_count()
    replay(whole, logs[half:], 4)
    want = landmarks(whole)
    assert len(want) == 4  # two signs in each town
    got: dict[int, bytes] = {}
    applied, pendings = [], []
    cps = []
    for i, part in enumerate(PARTS):
        split(cp, db_of(MatcherService, tmp_path, part), part, MATCHER, first=i == 0)
        svc = open_part(MatcherService, tmp_path, part)
        assert svc.instance != whole.instance  # a new producer
        assert read_log(svc.db_path, "assoc") == []
        pendings.append(svc.state.pending_count())
        tiles = svc.db.execute("SELECT DISTINCT tile FROM pending").fetchall()
        assert all(in_part(LogEntry("obs", "x", t, 1, 1, b""), part) for (t,) in tiles)
        replay(svc, [e for e in logs[half:] if in_part(e, part)], 4)
        got.update(landmarks(svc))
        applied.append(svc.counters.get("entries_applied", 0))
        cps.append(checkpoint(svc, tmp_path / f"part{i}.sqlite"))
        svc.db.close()
    assert got == want  # the same landmarks, the same sums to the bit
    assert sum(pendings) == pending > 0 and min(pendings) > 0
    assert sum(applied) == whole.counters["entries_applied"]  # counters in the first part
    # a vehicle on probation has held "not seen" reports in both parts, each numbered 0 on
    for i, cp_i in enumerate(cps):
        with sqlite3.connect(cp_i) as c:
            lid = c.execute("SELECT id FROM landmarks ORDER BY id LIMIT 1").fetchone()[0]
            c.execute("INSERT INTO held_absences VALUES ('veh-h', 0, ?, ?, ?, 5)", (i, lid, T0))
    # joined back: the whole's landmarks, and it goes on like the whole
    merge(cps, db_of(MatcherService, tmp_path / "joined", []), MATCHER)
    joined = open_part(MatcherService, tmp_path / "joined", [])
    assert landmarks(joined) == want
    assert [r[0] for r in joined.state.held_absences["veh-h"]] == [0, 1]  # both kept
    assert joined.counters["entries_applied"] == whole.counters["entries_applied"]


def test_a_solver_cut_in_two_publishes_what_the_whole_does(tmp_path, logs) -> None:
    m = open_matcher(tmp_path / "m")
    replay(m, logs, 4)
    assoc = read_log(m.db_path, "assoc")
    m.db.close()
    half = len(assoc) // 2
    whole = open_part(SolverService, tmp_path / "whole", [])
    replay(whole, assoc[:half], 3)  # type: ignore[arg-type]
    cp = checkpoint(whole, tmp_path / "s.sqlite")
    at_split = published(read_log(whole.db_path, "update"))
    replay(whole, assoc[half:], 3)  # type: ignore[arg-type]
    want = landmarks(whole)
    assert len(want) == 4
    got: dict[int, bytes] = {}
    cps = []
    for i, part in enumerate(PARTS):
        split(cp, db_of(SolverService, tmp_path, part), part, SOLVER, first=i == 0)
        svc = open_part(SolverService, tmp_path, part)
        assert all(in_part(LogEntry("obs", "x", lm.home, 1, 1, b""), part)
                   for lm in svc.state.landmarks.values())  # fmt: skip
        # a new update log opens with the part's published map (a publisher reading it
        # from its start gets the whole of it), once
        svc.start_log()
        mine = {
            i: v for i, v in at_split.items() if in_part(LogEntry("u", "x", v[0], 1, 1, b""), part)
        }
        assert mine and published(read_log(svc.db_path, "update")) == mine
        head = svc.writer.gseq
        svc.start_log()
        assert svc.writer.gseq == head
        replay(svc, [e for e in assoc[half:] if in_part(e, part)], 3)  # type: ignore[arg-type]
        got.update(landmarks(svc))
        cps.append(checkpoint(svc, tmp_path / f"s{i}.sqlite"))
        svc.db.close()
    assert got == want
    merge(cps, db_of(SolverService, tmp_path / "joined", []), SOLVER)
    assert landmarks(open_part(SolverService, tmp_path / "joined", [])) == want


@pytest.mark.parametrize(
    ("stops", "lag", "same"),
    [((34, 34), 60.0, True), ((24, 34), 60.0, False), ((24, 34), 3.0, True)],
    ids=["one_position", "apart", "apart_short_lag"],
)
def test_parts_joined_at_one_position_go_on_as_the_whole(tmp_path, stops, lag, same) -> None:
    """Why a merge brings its parts to one position of ingest's log (``hdmap region
    merge``, :func:`hdmap.ops.region.cut_at_one_position`). Cut at the 20th entry; town
    1's passes from the 25th see a new sign. Joined at one position (both parts at the
    34th), the joined matcher goes on as the whole: the same landmarks, gating positions
    to the bit. Joined apart (town 1's part stopped at the 24th), it applies town 1's
    backlog (5 passes, 4 s of capture time apart) against the other part's later clock,
    within ``tick_lag_s`` of it: one gating tick where the whole gave each pass its own,
    and the map differs (millimetres here); with a lag shorter than the passes' spacing
    the backlog's passes have ticks of their own and it does not."""
    config = matcher_config({"tick_lag_s": lag})
    gen = open_matcher(tmp_path / "gen")
    entries = traffic(gen, late=True)
    gen.db.close()
    whole = open_matcher(tmp_path / "whole", config)
    replay(whole, entries[:20], 4)
    cp = checkpoint(whole, tmp_path / "m.sqlite")
    replay(whole, entries[20:], 4)
    cps = []
    for i, (part, stop) in enumerate(zip(PARTS, stops, strict=True)):
        split(cp, db_of(MatcherService, tmp_path, part), part, MATCHER, first=i == 0)
        svc = MatcherService(ServiceOptions(data_dir=tmp_path, region=tuple(part)), config)
        svc.pubs = Sink()  # type: ignore[assignment]
        replay(svc, [e for e in entries[20:stop] if in_part(e, part)], 4)
        cps.append(checkpoint(svc, tmp_path / f"part{i}.sqlite"))
        svc.db.close()
    merge(cps, db_of(MatcherService, tmp_path / "joined", []), MATCHER)
    joined = open_matcher(tmp_path / "joined", config)
    replay(joined, entries[min(stops) :], 4)  # what a part applied is skipped (offsets)
    assert len(whole.state.landmarks) == 5  # the late sign included
    assert (landmark_digest(joined) == landmark_digest(whole)) is same
