"""Gating ticks (hdmap/mapping/tick.py): the units of one tick are associated with the
landmarks as the tick found them (plus their own pass's new ones), what they touched is
re-solved when the next tick begins, and the map depends only on the entries, not on how
they were batched or on a restart in the middle of a tick. In-process matcher on real
SQLite (scene of tests/support/services.py: passes along a road, 10 rays each)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from hdmap.mapping.tick import tick_of, visible
from schemas import LogEntry, ObsGroup
from schemas.ids import pass_key
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


def test_a_new_landmark_is_seen_by_its_own_pass_at_once_and_by_others_next_tick(
    tmp_path: Path,
) -> None:
    m = matcher(tmp_path)
    area = m.matching.area(tile_of(m.opts.zoom))
    m._apply_in_transaction([entry(m, 1, "veh-a", T0)])
    (lid,) = m.state.landmarks
    assert m.state.tick_born == {lid: pass_key("veh-a", 1)}
    assert [lm.id for lm in visible(m.matching, area, pass_key("veh-a", 1))] == [lid]
    assert visible(m.matching, area, pass_key("veh-b", 2)) == []
    x0 = m.state.landmarks[lid].x.copy()  # the initiating triangulation
    # another vehicle in the same tick: the landmark is not its candidate
    m._apply_in_transaction([entry(m, 2, "veh-b", T0 + 0.3)])
    assert m.counters.get("associated", 0) == 0
    np.testing.assert_array_equal(m.state.landmarks[lid].x, x0)  # not re-solved yet
    assert m.state.landmarks[lid].facing[3] == 0  # nor its facing (unknown when started)
    assert lid in m.state.tick_touched
    # a pass in the next tick: the tick ended (re-solved, merged), its rays link
    m._apply_in_transaction([entry(m, 3, "veh-c", T0 + 1.5)])
    assert m.counters["associated"] >= 8
    assert set(m.state.tick_born.values()) <= {pass_key("veh-c", 3)}
    assert m.state.landmarks[lid].facing[3] == 1  # re-solved when the tick ended


def test_the_map_is_the_same_however_batched_and_across_a_restart_in_a_tick(
    tmp_path: Path,
) -> None:
    """Forty passes of eight vehicles at two signs, 0.3 s apart, every fourth pass sending
    a second upload 0.1 s after its first: ticks of three to six units, a pass's second
    upload in the tick where its first started the landmarks. Batches of 1, 7 and all,
    associated one by one or together, and a restart while a tick is open, give one
    map."""
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
    assert redone > 0  # the second uploads saw their pass's new landmarks
    svc = matcher(tmp_path / "restart")
    replay(svc, entries[:13], 5)
    assert svc.state.tick_touched  # a tick is open
    svc.db.close()
    svc = matcher(tmp_path / "restart")  # its marks come back from the database
    assert svc.state.tick_touched
    replay(svc, entries, 5)  # the first 13 are skipped (applied)
    digests.add(landmark_digest(svc))
    assert len(digests) == 1


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
    """Uploads a fraction of a second out of order share the live tick; a day's drive
    uploaded late goes by its own times (its passes do not pile into one tick)."""
    m = matcher(tmp_path)
    now = T0 + 0.9
    assert tick_of(m.matching, now - 0.5, now) == tick_of(m.matching, now, now) == int(T0)
    assert tick_of(m.matching, now - 1.0, now) == int(T0)  # at most tick_s behind
    late = now - 86400.0
    assert tick_of(m.matching, late, now) == int(late)
    assert tick_of(m.matching, late + 60.0, now) != tick_of(m.matching, late, now)
    assert tick_of(matcher(tmp_path / "z", tick_s=0.0).matching, now, now) is None
