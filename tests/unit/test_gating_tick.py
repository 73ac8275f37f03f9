"""Gating ticks (hdmap/mapping/tick.py): the units of one tick are associated with the
landmarks as the tick found them, the rays they leave waiting start landmarks and what
they touched is re-solved when the next tick begins, and the map depends only on the
entries, not on how they were batched or on a restart in the middle of a tick.
In-process matcher on real SQLite (scene of tests/support/services.py: passes along a
road, 10 rays each)."""

from __future__ import annotations

import sqlite3
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from hdmap.mapping.tick import candidates, tick_of
from hdmap.runtime.store import id_to_sql, u64_to_i64
from schemas import LogEntry, ObsGroup
from services.matcher.replay import landmark_digest, open_matcher, replay
from services.matcher.service import MatcherConfig, MatcherService
from tests.support.services import CLS, SIGN, sign_rays, tile_of

T0 = float(int(time.time()) - 3600)  # a tick starts here (1 s ticks)
OTHER = SIGN + np.array([-8.0, 6.0, 0.0])


def entry(
    m: MatcherService, seq: int, vehicle: str, at: float, both: bool = False, part: int = 0
) -> LogEntry:
    """One pass (id ``seq``) of ``vehicle`` at the sign (``both``: and at a sign of another
    class 10 m from it, in the same images), its rays captured over the 2 s up to ``at``
    (event time), stamped by ingest a second later; ``part`` > 0: a later upload of the
    pass (other images)."""
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    obs = sign_rays(frame, seq, np.random.default_rng(seq + 77 * part), image0=20 * part)
    if both:
        o2 = sign_rays(frame, seq, np.random.default_rng(seq + 1000), at=OTHER, image0=20 * part)
        o2 = replace(o2, obs_id=o2.obs_id + 500, sign_class=o2.sign_class + 1)
        obs = type(obs).concat([obs, o2])
    obs = replace(obs, t=at - np.linspace(2.0, 0.0, len(obs)))
    body = ObsGroup(vehicle, seq, seq, at + 1.0, obs).to_bytes()
    return LogEntry("obs", "ingest-t", tile, seq, seq, body)


def matcher(path: Path, tick_s: float = 1.0, ahead: int = 32) -> MatcherService:
    return open_matcher(path, MatcherConfig(tick_s=tick_s, associate_ahead=ahead))


def traffic(path: Path) -> list[LogEntry]:
    """Forty passes of eight vehicles at two signs, 0.3 s apart, every fourth pass sending
    a second upload 0.1 s after its first, in log order."""
    m0 = matcher(path)
    entries = []
    for k in range(40):
        entries.append(entry(m0, k + 1, f"veh-{k % 8}", T0 + 0.3 * k, both=True))
        if k % 4 == 0:
            entries.append(entry(m0, k + 1, f"veh-{k % 8}", T0 + 0.3 * k + 0.1, True, part=1))
    m0.db.close()
    return [replace(e, seq=n + 1, gseq=n + 1) for n, e in enumerate(entries)]


def test_a_landmark_is_born_when_its_tick_ends_and_takes_the_tick_s_rays_of_other_passes(
    tmp_path: Path,
) -> None:
    """Two passes of two vehicles at one sign in one tick: nothing is started while the tick
    lasts (their rays wait, untried); when a unit of the next tick comes, the first pass
    (by pass key) starts the landmark, the other's rays are adopted, the landmark is
    re-solved, and the new unit's rays link to it."""
    m = matcher(tmp_path)
    m._apply_in_transaction([entry(m, 1, "veh-a", T0)])
    m._apply_in_transaction([entry(m, 2, "veh-b", T0 + 0.3)])
    assert not m.state.landmarks
    assert candidates(m.matching, tile_of(m.opts.zoom)).lms == []
    pool = m.state.pending[tile_of(m.opts.zoom)]
    assert len(pool) == 20 and not pool.tried.any()  # tried when the tick ends
    m._apply_in_transaction([entry(m, 3, "veh-c", T0 + 1.5)])
    (lid,) = m.state.landmarks
    assert m.counters["created"] == 1
    assert m.counters["adopted"] >= 8  # the other pass's rays of the tick
    assert m.state.landmarks[lid].facing[3] == 1  # re-solved when the tick ended
    assert m.counters["associated"] >= 8  # the next tick's unit sees it


def test_the_map_is_the_same_however_batched_and_across_a_restart_in_a_tick(
    tmp_path: Path,
) -> None:
    """Forty passes of eight vehicles at two signs, 0.3 s apart, every fourth pass sending
    a second upload 0.1 s after its first: ticks of three to six units, a pass's second
    upload in its first's tick. Batches of 1, 7 and all, associated one by one or
    together, and a restart while a tick is open (rays waiting to be tried, or landmarks
    to re-solve), give one map."""
    entries = traffic(tmp_path / "gen")
    digests = set()
    redone = 0
    for batch, ahead in ((1, 32), (7, 32), (len(entries), 32), (len(entries), 1)):
        svc = matcher(tmp_path / f"b{batch}-{ahead}", ahead=ahead)
        replay(svc, entries, batch)
        digests.add(landmark_digest(svc))
        assert sorted(lm.cls for lm in svc.state.landmarks.values()) == [CLS, CLS + 1]
        redone += svc.counters.get("assoc_redone", 0)
        svc.db.close()
    assert redone == 0  # no landmark is born inside a tick: what was associated ahead holds
    for cut in (3, 13):  # in the first tick (rays waiting, untried) and in a later one
        svc = matcher(tmp_path / f"restart-{cut}")
        replay(svc, entries[:cut], 5)
        marks = (set(svc.state.tick_touched), _untried(svc))
        assert marks[0] if cut == 13 else marks[1]  # a tick is open, with marks to keep
        svc.db.close()
        svc = matcher(tmp_path / f"restart-{cut}")  # its marks come back from the database
        assert (set(svc.state.tick_touched), _untried(svc)) == marks
        replay(svc, entries, 5)  # the first ones are skipped (applied)
        digests.add(landmark_digest(svc))
        svc.db.close()
    assert len(digests) == 1


def _untried(svc: MatcherService) -> dict[str, list[int]]:
    """The pool rows not yet tried as seeds, by tile."""
    return {
        t: np.flatnonzero(~p.tried).tolist()
        for t, p in svc.state.pending.items()
        if not p.tried.all()
    }


def test_facings_are_what_association_saw_after_a_restart(tmp_path: Path) -> None:
    m = matcher(tmp_path)
    replay(m, [entry(m, k + 1, f"veh-{k}", T0 + 5.0 * k) for k in range(6)], 2)
    faced = {i: lm.facing.copy() for i, lm in m.state.landmarks.items()}
    assert any(f[3] > 0 for f in faced.values())  # known from enough rays
    m.db.close()
    again = matcher(tmp_path)
    for i, f in faced.items():
        np.testing.assert_array_equal(again.state.landmarks[i].facing, f)


def test_a_unit_a_little_late_joins_the_clocks_tick_a_late_one_has_its_own(
    tmp_path: Path,
) -> None:
    """Uploads seconds out of order share the live tick; a day's drive uploaded late goes
    by its own times (its passes do not pile into one tick)."""
    m = matcher(tmp_path)
    now = T0 + 0.9
    lag = m.matching.config.tick_lag_s
    assert tick_of(m.matching, now - 0.5, now) == tick_of(m.matching, now, now) == int(T0)
    assert tick_of(m.matching, now - lag, now) == int(T0)  # at most tick_lag_s behind
    assert tick_of(m.matching, now - lag - 0.5, now) == int(now - lag - 0.5)
    late = now - 86400.0
    assert tick_of(m.matching, late, now) == int(late)
    assert tick_of(m.matching, late + 60.0, now) != tick_of(m.matching, late, now)
    assert tick_of(matcher(tmp_path / "z", tick_s=0.0).matching, now, now) is None


class _NeverKept(dict):
    """A cache that keeps nothing: every unit builds its candidate arrays anew."""

    def __setitem__(self, key, value) -> None:
        pass


def test_candidate_arrays_kept_for_a_tick_give_the_map_built_anew_each_unit(
    tmp_path: Path,
) -> None:
    """A tile's candidate arrays are kept until a landmark is started, removed or
    re-solved (``gating_version``); the map is the one rebuilding them for every unit
    gives, to the bit."""
    entries = traffic(tmp_path / "gen")
    bits = []
    for name, cache in (("kept", None), ("anew", _NeverKept())):
        svc = matcher(tmp_path / name)
        if cache is not None:
            svc.matching.candidate_arrays = cache
        replay(svc, entries, 7)
        lms = [svc.state.landmarks[i] for i in sorted(svc.state.landmarks)]
        bits.append([(lm.id, lm.x.tobytes(), lm.cov.tobytes(), lm.facing.tobytes()) for lm in lms])
        if cache is None:  # kept arrays are in use, and as new as the landmarks
            version, kept = svc.matching.candidate_arrays[tile_of(svc.opts.zoom)]
            assert version == svc.state.gating_version
            np.testing.assert_array_equal(
                kept.x, svc.frames(tile_of(svc.opts.zoom)).from_ecef(np.array([lm.x for lm in lms]))
            )
        svc.db.close()
    assert bits[0] == bits[1]


def _stored(svc: MatcherService) -> tuple[set, set]:
    """The tick marks and the untried rays as the matcher's database holds them."""
    conn = sqlite3.connect(f"file:{svc.db_path}?mode=ro", uri=True)
    try:
        marks = set(conn.execute("SELECT id, touched, counted FROM tick").fetchall())
        untried = set(conn.execute("SELECT vehicle, obs_id FROM untried").fetchall())
    finally:
        conn.close()
    return marks, untried


def _in_memory(svc: MatcherService) -> tuple[set, set]:
    st = svc.state
    ids = st.tick_touched | st.tick_counted
    marks = {(id_to_sql(i), int(i in st.tick_touched), int(i in st.tick_counted)) for i in ids}
    untried = {
        (v, i)
        for p in st.pending.values()
        for v, i in zip(
            p.vehicle[~p.tried].tolist(), u64_to_i64(p.obs.obs_id[~p.tried]).tolist(), strict=True
        )
    }
    return marks, untried


def test_the_stored_tick_marks_and_untried_rays_follow_memory_after_every_transaction(
    tmp_path: Path,
) -> None:
    """The tick's marks and the untried rays are written as they change, not rewritten
    whole in every transaction: after each one (ticks opening and ending, rays pooled,
    tried, adopted and used, a landmark touched for the first time in the middle of a
    tick) the database holds what memory holds. Four passes a tick; the first of each
    sees one sign, the others both."""
    m0 = matcher(tmp_path / "gen")
    entries = [entry(m0, k + 1, f"veh-{k % 8}", T0 + 0.25 * k, both=k % 4 != 0) for k in range(24)]
    m0.db.close()
    svc = matcher(tmp_path / "m")
    seen_untried = seen_marks = 0
    for i in range(len(entries)):
        svc._apply_in_transaction(svc._unapplied(entries[i : i + 1]))
        marks, untried = _in_memory(svc)
        assert _stored(svc) == (marks, untried)
        seen_marks += bool(marks)
        seen_untried += bool(untried)
    assert seen_marks and seen_untried  # both had something to keep along the way


def _rays_linked(svc: MatcherService) -> dict[int, int]:
    """Rays in each landmark's gating sums (the held links added)."""
    lms = [svc.state.landmarks[i] for i in sorted(svc.state.landmarks)]
    n = svc.matching.sums.n_obs(np.array([lm.row for lm in lms], np.int64))
    return {lm.id: int(k) for lm, k in zip(lms, n, strict=True)}


def test_a_restart_after_any_transaction_keeps_the_links_held_for_the_tick(
    tmp_path: Path,
) -> None:
    """A transaction saves the links it held for the gating sums (they are added when the
    tick ends, not at every save); a matcher restarted after every transaction, inside
    ticks, ends with every ray linked and the map of one that never stopped (a restart
    reopens the open passes as quiet from its clock on: to the mm, not the bit)."""
    entries = traffic(tmp_path / "gen")
    ref = matcher(tmp_path / "ref")
    replay(ref, entries, 1)
    want = (_rays_linked(ref), landmark_digest(ref))
    ref.db.close()
    held_at_a_start = 0
    for i in range(len(entries)):
        svc = matcher(tmp_path / "restarted")
        held_at_a_start += bool(svc.matching.unsummed)  # held links came back
        svc._apply_in_transaction(svc._unapplied(entries[i : i + 1]))
        svc.db.close()
    assert held_at_a_start > len(entries) // 2
    again = matcher(tmp_path / "restarted")
    assert (_rays_linked(again), landmark_digest(again)) == want
