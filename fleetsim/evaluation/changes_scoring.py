"""Scoring a map against a world whose signs change (issue 21's evaluation; pure, no I/O).

At each check (the map as a vehicle reads it after a round of passes, at event time ``t``)
every change event whose time has come (:meth:`fleetsim.changes.Change.events`) is
*reflected* when each sign it puts up is held by a landmark whose existence is not
doubtful (one-to-one pairing with the signs standing at ``t``,
:func:`fleetsim.truth.match_landmarks`, ``match_m``; confirmed landmarks preferred) and no
landmark of a sign it took down's class sits within ``match_m`` of that sign's place
unpaired (a landmark that moved with a moved sign and pairs with it is fine); *located*
when, besides, the landmarks that hold the new signs are confirmed (their horizontal sigma
under the solver's bound). The passes a change needed are those that drove past it from
its time until the first check that found it reflected (located): passes whose camera had
the sign it took down or put up in view, from the side the sign faces, in at least
``min_frames`` frames (:func:`vehicle.absence.expected` on the simulator's true camera
poses; a pass on the cross street or the other way does not count); a change not
reflected by the end counts as not reflected (censored, listed).

False revocations: signs no change touched that a confirmed landmark held at one check
and no landmark (not doubtful) held at a later one (the map lost a standing sign).
Calibration: every published landmark at every check, its ``p_exist`` against whether a
sign stands there.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetsim.changes import ChangeSchedule
from fleetsim.truth import match_landmarks
from fleetsim.world import World
from schemas import STATUS_CONFIRMED
from schemas.map import MapLandmarks
from vehicle.absence import FrameDetections, Frames, MapSigns, ViewModel, expected

Array = NDArray[np.float64]


@dataclass
class EventRecord:
    """One change event being followed."""

    change: int
    """Index into the schedule's changes."""
    kind: str
    t: float
    present: tuple[int, ...]
    gone: tuple[int, ...]
    places: MapSigns
    """The signs it takes down and puts up, as the view test reads them."""
    passes: int = 0
    """Passes past the place since ``t`` so far."""
    reflected_at: float | None = None
    """Event time of the check that first found it reflected."""
    passes_to_reflect: int | None = None
    hours_to_reflect: float | None = None
    passes_to_locate: int | None = None
    trace: list[tuple[int, list[float], int]] = field(default_factory=list)
    """Per check from its time until reflected: (passes so far, ``p_exist`` of the
    landmarks left where a sign it took down was, signs it puts up held by any landmark)."""
    waiting_for: list[int] = field(default_factory=list)
    """At the latest check: the signs it puts up that no confirmed landmark held, and the
    landmarks still standing where a sign it took down was."""


@dataclass
class ChangeScorer:
    """Follows a schedule's events over the checks of one run."""

    world: World
    schedule: ChangeSchedule
    match_m: float = 5.0
    view: ViewModel = field(default_factory=ViewModel)
    events: list[EventRecord] = field(default_factory=list)
    held: dict[int, int] = field(default_factory=dict)
    """Unchanged sign id -> the landmark id that last held it (confirmed)."""
    lost: dict[int, tuple[float, int]] = field(default_factory=dict)
    """Unchanged sign id -> (check time, landmark id) when the map lost it."""
    calibration: list[tuple[float, int]] = field(default_factory=list)
    """(p_exist, a sign stands there) per published landmark per check."""

    def __post_init__(self) -> None:
        every, _up, _down = self.schedule.lifetimes(self.world.signs)
        self._every = every
        self._row = {int(i): k for k, i in enumerate(every.id.tolist())}
        touched: set[int] = set()
        for k, c in enumerate(self.schedule.changes):
            touched |= {c.old_id, c.new_id} - {-1}
            for e in c.events():
                rows = np.array([self._row[i] for i in (*e.gone, *e.present)], np.int64)
                places = MapSigns(
                    id=every.id[rows].astype(np.int64),
                    en=every.position[rows, :2].copy(),
                    sign_class=every.sign_class[rows].astype(np.int64),
                    facing_deg=every.facing_azimuth_deg[rows],
                )
                self.events.append(EventRecord(k, c.kind, e.t, e.present, e.gone, places))
        self.unchanged = {int(i) for i in self.world.signs.id.tolist()} - touched

    def note_pass(self, t: float, frame_t: Array, camera_en: Array, yaw_deg: Array) -> None:
        """A pass that started at ``t``: its camera's true poses per frame (times, (F, 2)
        East/North, yaw deg clockwise from North)."""
        frames = Frames(np.asarray(frame_t, float), np.asarray(camera_en, float), yaw_deg)
        none = FrameDetections(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        for e in self.events:
            if e.passes_to_locate is None and t >= e.t and len(frames.t):
                seen = expected(frames, e.places, none, self.view).frames_in_view
                if np.any(seen >= self.view.min_frames):
                    e.passes += 1

    def check(self, t: float, lm: MapLandmarks) -> None:
        """The map ``lm`` as read at event time ``t`` (after every pass up to ``t``)."""
        now = self.schedule.world_at(self.world, t)
        confirmed = lm.status == STATUS_CONFIRMED
        m = match_landmarks(now, lm.lat, lm.lon, lm.h, lm.sign_class, self.match_m, confirmed)
        sign_ids = now.signs.id[m.sign_row].tolist()
        doubtful = np.asarray(lm.exist_state) == 2
        holder = {
            int(s): int(lm.id[k])
            for s, k in zip(sign_ids, m.landmark.tolist(), strict=True)
            if not doubtful[k]
        }
        located = {
            int(s) for s, k in zip(sign_ids, m.landmark.tolist(), strict=True) if confirmed[k]
        }
        paired = np.zeros(len(lm), bool)
        paired[m.landmark] = True
        en = now.frame.from_geodetic(lm.lat, lm.lon, lm.h).reshape(-1, 3)[:, :2]
        for e in self.events:
            if t < e.t:
                continue
            if e.passes_to_locate is None and e.reflected_at is not None:
                if all(i in located for i in e.present):
                    e.passes_to_locate = e.passes
            if e.reflected_at is not None:
                continue
            rows = [k for i in e.gone for k in self._left_at(i, en, lm.sign_class, paired)]
            left = [int(lm.id[k]) for k in rows]
            e.waiting_for = [i for i in e.present if i not in holder] + left
            anyone = sum(i in sign_ids for i in e.present)
            e.trace.append((e.passes, [round(float(lm.p_exist[k]), 4) for k in rows], anyone))
            if not e.waiting_for:
                e.reflected_at = t
                e.passes_to_reflect = e.passes
                e.hours_to_reflect = (t - e.t) / 3600.0
                if all(i in located for i in e.present):
                    e.passes_to_locate = e.passes
        for s in self.unchanged:
            if s in located and s in holder:
                self.held[s] = holder[s]
                self.lost.pop(s, None)
            elif s in self.held and s not in holder and s not in self.lost:
                self.lost[s] = (t, self.held[s])
        for p, ok in zip(np.asarray(lm.p_exist, float).tolist(), paired.tolist(), strict=True):
            if p > 0:
                self.calibration.append((p, int(ok)))

    def _left_at(self, sign_id: int, en: Array, cls: NDArray, paired: NDArray) -> list[int]:
        """Rows of the unpaired landmarks of the gone sign's class at its place."""
        r = self._row[sign_id]
        near = np.hypot(*(en - self._every.position[r, :2]).T) <= self.match_m
        return np.flatnonzero(near & ~paired & (cls == self._every.sign_class[r])).tolist()


def _stats(values: list[int], unreflected: int) -> dict:
    """Median and p95 of passes to reflect, the unreflected counted as never (inf)."""
    a = np.array(values + [np.inf] * unreflected, float)
    if a.size == 0:
        return {"median": None, "p95": None, "n": 0, "unreflected": 0}
    med, p95 = np.percentile(a, [50, 95], method="higher")
    return {
        "median": None if np.isinf(med) else float(med),
        "p95": None if np.isinf(p95) else float(p95),
        "n": int(a.size),
        "unreflected": unreflected,
    }


KIND_KEYS = {"remove": "removal", "move": "move", "replace": "replacement", "add": "addition"}


def event_key(kind: str, present) -> str:
    """The summary key of an event: its kind's (``removal``, ...), a temporary sign's
    ``temporary_up`` (it puts a sign up) or ``temporary_down``."""
    return KIND_KEYS.get(kind, "temporary_" + ("up" if present else "down"))


def passes_keys(events: list[tuple[str, int | None, int | None]]) -> dict:
    """Per summary key, the median and p95 passes to reflect and to locate
    (``<key>_located_...``), the events and those never reflected, from (key, passes to
    reflect, passes to locate) per event (None: never)."""
    out: dict = {}
    for j, suffix in ((1, ""), (2, "_located")):
        groups: dict[str, tuple[list[int], int]] = {}
        for e in events:
            done, left = groups.get(e[0], ([], 0))
            groups[e[0]] = (done, left + 1) if e[j] is None else ([*done, e[j]], left)
        for key, (done, left) in sorted(groups.items()):
            st = _stats(done, left)
            out[f"{key}{suffix}_median_passes"] = st["median"]
            out[f"{key}{suffix}_p95_passes"] = st["p95"]
            out[f"{key}{suffix}_unreflected"] = st["unreflected"]
            if not suffix:
                out[f"{key}_events"] = st["n"]
    return out


def summary(scorer: ChangeScorer, rogue_landmarks: set[int]) -> dict:
    """The evaluation's keys: per kind the median and p95 passes to reflect (removals,
    moves, replacements, additions; a temporary sign's coming and going separately) and
    to locate (:func:`passes_keys`), false revocations and those of landmarks the rogue
    vehicle reported absent, and the existence probability's calibration."""
    out = passes_keys(
        [
            (event_key(e.kind, e.present), e.passes_to_reflect, e.passes_to_locate)
            for e in scorer.events
        ]
    )
    out["false_revocations"] = len(scorer.lost)
    out["rogue_revocations"] = sum(1 for _t, lid in scorer.lost.values() if lid in rogue_landmarks)
    out["calibration"] = calibration(scorer.calibration)
    return out


def calibration(pairs: list[tuple[float, int]], edges=(0.0, 0.2, 0.5, 0.8, 0.95, 1.0)) -> dict:
    """Reliability of ``p_exist``: per bin the mean probability and the share that stood,
    and the Brier score."""
    if not pairs:
        return {"brier": None, "bins": []}
    p = np.array([x[0] for x in pairs])
    y = np.array([x[1] for x in pairs], float)
    bins = []
    for lo, hi in itertools.pairwise(edges):
        sel = (p >= lo) & ((p < hi) if hi < 1.0 else (p <= hi))
        if sel.any():
            bins.append(
                {
                    "p_lo": lo,
                    "p_hi": hi,
                    "n": int(sel.sum()),
                    "mean_p": float(p[sel].mean()),
                    "stood": float(y[sel].mean()),
                }
            )
    return {"brier": float(np.mean((p - y) ** 2)), "n": int(p.size), "bins": bins}
