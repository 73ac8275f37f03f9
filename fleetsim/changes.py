"""Scheduled changes to a world's signs: taken down, moved, replaced, put up, temporary.

A :class:`ChangeSchedule` lists :class:`Change` s at event times (s, the fleet's clock) and
holds the signs they put up. Every sign that ever stands has its own id, never reused: a
moved or replaced sign is a new sign and the old one is gone. A sign taken down at ``t``
stands before ``t``, one put up at ``t`` from ``t`` on, a temporary one in ``[t, t_end)``.
:meth:`ChangeSchedule.signs_at` is the world's signs table as it stands at a time: its rows
still standing (in their order), then the new ones; with no change in effect, itself.

>>> from fleetsim.world import straight_road
>>> w = straight_road()
>>> s = ChangeSchedule().with_replacement(w.signs, 0, 100.0, CATALOG.code("stop"))
>>> [s.signs_at(w.signs, t).id.tolist() for t in (99.0, 100.0)]
[[0], [1]]
>>> s.changes[0].events()
(ChangeEvent(t=100.0, present=(1,), gone=(0,)),)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.random import Generator
from numpy.typing import ArrayLike, NDArray

from fleetsim.world import Signs, World, roadside, segment_distance
from hdmap.geo.signs import CATALOG, SignCatalog

Array = NDArray[np.float64]
Kind = Literal["remove", "move", "replace", "add", "temporary"]
KINDS: tuple[Kind, ...] = ("remove", "move", "replace", "add", "temporary")
_TAKES_DOWN = ("remove", "move", "replace")
_FIELDS = ("id", "sign_class", "position", "facing", "panel_height_m")


@dataclass(frozen=True)
class ChangeEvent:
    """What the map should show once it has caught up with one event of a change: the
    sign ids that should be in it from ``t`` on (``present``) and those ``gone``."""

    t: float
    present: tuple[int, ...]
    gone: tuple[int, ...]


@dataclass(frozen=True)
class Change:
    """One change at time ``t``: ``old_id`` taken down (-1: none; for remove, move and
    replace), ``new_id`` put up (-1: none; for all but remove); a temporary sign is taken
    down again at ``t_end``."""

    kind: Kind
    t: float
    old_id: int = -1
    new_id: int = -1
    t_end: float | None = None

    def __post_init__(self) -> None:
        if not (
            self.kind in KINDS
            and (self.old_id >= 0) == (self.kind in _TAKES_DOWN)
            and (self.new_id >= 0) == (self.kind != "remove")
            and (self.t_end is None) == (self.kind != "temporary")
            and (self.t_end is None or self.t_end > self.t)
        ):
            raise ValueError(f"not a valid change: {self}")

    def events(self) -> tuple[ChangeEvent, ...]:
        """The truth to score: one event, two for a temporary sign (up, then down)."""
        old = (self.old_id,) if self.old_id >= 0 else ()
        new = (self.new_id,) if self.new_id >= 0 else ()
        up = ChangeEvent(self.t, new, old)
        return (up,) if self.t_end is None else (up, ChangeEvent(self.t_end, (), new))


def _concat(a: Signs, b: Signs) -> Signs:
    return Signs(*(np.concatenate([getattr(a, f), getattr(b, f)]) for f in _FIELDS))


def _no_signs() -> Signs:
    return Signs.build([], np.zeros((0, 3)), [])


@dataclass(frozen=True)
class ChangeSchedule:
    """Changes to a world's signs and the signs they put up (rows of ``new_signs``).
    The ``with_*`` methods give a new schedule with one more change (``signs``: the
    world's; a new sign gets the next free id)."""

    changes: tuple[Change, ...] = ()
    new_signs: Signs = field(default_factory=_no_signs)

    def __post_init__(self) -> None:
        new = sorted(c.new_id for c in self.changes if c.new_id >= 0)
        if new != sorted(self.new_signs.id.tolist()) or len(set(new)) != len(new):
            raise ValueError("each new sign must be put up by exactly one change")
        down = [c for c in self.changes if c.old_id >= 0]
        up = {c.new_id: c for c in self.changes if c.new_id >= 0}
        if len({c.old_id for c in down}) != len(down) or any(
            c.old_id in up and not (up[c.old_id].t_end is None and up[c.old_id].t < c.t)
            for c in down
        ):
            raise ValueError("a sign is taken down once, after it is put up, if not temporary")

    def check(self, signs: Signs) -> None:
        """Raise ValueError unless this schedule fits the world's ``signs`` (:meth:`lifetimes`)."""
        self.lifetimes(signs)

    def lifetimes(self, signs: Signs) -> tuple[Signs, Array, Array]:
        """Every sign that ever stands (the world's ``signs``, then ``new_signs``), the time
        it is put up (-inf: from the start) and taken down (inf: never). ValueError unless
        the schedule fits ``signs``: new ids not theirs, signs taken down that stand."""
        every = _concat(signs, self.new_signs)
        if np.isin(self.new_signs.id, signs.id).any():
            raise ValueError("the schedule's new sign ids must not be the world's")
        up, down = np.full(len(every), -np.inf), np.full(len(every), np.inf)
        t = np.array([c.t for c in self.changes], float)
        end = np.array([np.inf if c.t_end is None else c.t_end for c in self.changes], float)
        old = every.index_of(np.array([c.old_id for c in self.changes], np.int64))
        new = every.index_of(np.array([c.new_id for c in self.changes], np.int64))
        takes_down = np.array([c.old_id >= 0 for c in self.changes], bool)
        if (old[takes_down] < 0).any():
            raise ValueError("the schedule takes down signs that never stand")
        up[new[new >= 0]], down[new[new >= 0]] = t[new >= 0], end[new >= 0]
        down[old[takes_down]] = t[takes_down]  # after: a new sign may be taken down later
        return every, up, down

    def signs_at(self, signs: Signs, t: float) -> Signs:
        """The world's ``signs`` as they stand at time ``t`` (module docstring)."""
        if not self.changes:
            return signs
        every, up, down = self.lifetimes(signs)
        standing = (up <= t) & (t < down)
        if standing[: len(signs)].all() and not standing[len(signs) :].any():
            return signs
        return every.take(np.flatnonzero(standing))

    def world_at(self, world: World, t: float) -> World:
        """``world`` with its signs as they stand at ``t`` (itself when none changed yet)."""
        s = self.signs_at(world.signs, t)
        return world if s is world.signs else world.with_signs(s)

    def events(self) -> list[ChangeEvent]:
        """Every change's events, by time."""
        return sorted((e for c in self.changes for e in c.events()), key=lambda e: e.t)

    def sign(self, signs: Signs, sign_id: int) -> Signs:
        """The one-row table of sign ``sign_id``, of the world's ``signs`` or put up here."""
        every = _concat(signs, self.new_signs)
        r = every.index_of(np.array([sign_id]))
        if r[0] < 0:
            raise ValueError(f"no sign {sign_id} in the world nor put up by the schedule")
        return every.take(r)

    def _put_up(self, signs: Signs, c: Change, new: Signs) -> ChangeSchedule:
        i = 1 + max(int(signs.id.max(initial=-1)), int(self.new_signs.id.max(initial=-1)))
        row = replace(new, id=np.array([i], np.int64))
        return ChangeSchedule((*self.changes, replace(c, new_id=i)), _concat(self.new_signs, row))

    def with_removal(self, signs: Signs, sign_id: int, t: float) -> ChangeSchedule:
        """Sign ``sign_id`` taken down at ``t``."""
        c = Change("remove", float(t), int(self.sign(signs, sign_id).id[0]))
        return ChangeSchedule((*self.changes, c), self.new_signs)

    def with_move(
        self, signs: Signs, sign_id: int, t: float, offset_m: ArrayLike, az_deg: float | None = None
    ) -> ChangeSchedule:
        """Sign ``sign_id`` moved by ``offset_m`` (ENU m, 2 or 3 components) at ``t``: a
        new sign, same class and panel, facing ``az_deg`` (None: as before)."""
        old, d = self.sign(signs, sign_id), np.zeros(3)
        d[: np.size(offset_m)] = np.ravel(offset_m)
        new = replace(old, position=old.position + d)
        if az_deg is not None:
            az = np.radians(az_deg)  # as Signs.build turns an azimuth into a facing
            new = replace(new, facing=np.array([[np.sin(az), np.cos(az), 0.0]]))
        return self._put_up(signs, Change("move", float(t), int(sign_id), 0), new)

    def with_replacement(
        self, signs: Signs, sign_id: int, t: float, sign_class: int, catalog: SignCatalog = CATALOG
    ) -> ChangeSchedule:
        """Sign ``sign_id`` replaced at ``t`` by a panel of class ``sign_class``, same place
        and facing."""
        old, c = self.sign(signs, sign_id), np.array([sign_class], np.int64)
        new = replace(old, sign_class=c, panel_height_m=catalog.heights(c))
        return self._put_up(signs, Change("replace", float(t), int(sign_id), 0), new)

    def with_addition(
        self, signs: Signs, t: float, new: Signs, t_end: float | None = None
    ) -> ChangeSchedule:
        """The one-row table ``new`` (e.g. of :meth:`Signs.build`) put up at ``t``, and
        taken down at ``t_end`` (None: never; else a temporary sign)."""
        end = None if t_end is None else float(t_end)
        c = Change("add" if end is None else "temporary", float(t), -1, 0, end)
        return self._put_up(signs, c, new)

    def describe(self, signs: Signs, catalog: SignCatalog = CATALOG) -> list[dict[str, Any]]:
        """Per change, a JSON-serialisable record for a report: kind, times, ids, events,
        the ``old`` and ``new`` sign (class, position ENU m, facing deg; None: no such sign)
        and how far it moved horizontally (``moved_m``; None unless both)."""
        every, out = self.lifetimes(signs)[0], []
        for c in self.changes:
            d: dict[str, Any] = {**asdict(c), "events": [asdict(e) for e in c.events()]}
            for side, i in (("old", c.old_id), ("new", c.new_id)):
                s = every.take(every.index_of(np.array([i])))
                name, az = catalog.by_code(int(s.sign_class[0])).name, s.facing_azimuth_deg[0]
                rec = {"class": name, "position": s.position[0].tolist(), "facing_deg": float(az)}
                d[side] = rec if i >= 0 else None
            both = d["old"] is not None and d["new"] is not None
            dxy = np.subtract(d["new"]["position"], d["old"]["position"])[:2] if both else None
            out.append({**d, "moved_m": None if dxy is None else float(np.hypot(*dxy))})
        return out

    def to_json(self) -> dict[str, Any]:
        """This schedule as JSON-serialisable values (:meth:`from_json` reads it back)."""
        rows = {f: getattr(self.new_signs, f).tolist() for f in _FIELDS}
        return {"changes": [asdict(c) for c in self.changes], "new_signs": rows}

    @staticmethod
    def from_json(data: dict[str, Any]) -> ChangeSchedule:
        """The schedule :meth:`to_json` wrote (after a JSON round trip: the same floats)."""
        s, ints = data["new_signs"], ("id", "sign_class")
        cols = [np.asarray(s[f], np.int64 if f in ints else float) for f in _FIELDS]
        cols[2:4] = [c.reshape(-1, 3) for c in cols[2:4]]  # position, facing
        return ChangeSchedule(tuple(Change(**c) for c in data["changes"]), Signs(*cols))


# --- a random schedule ---------------------------------------------------------------


@dataclass(frozen=True)
class Placement:
    """Where :func:`random_schedule` puts signs, as :func:`fleetsim.world.demo_town` does:
    ``lateral_m`` right of the lane centre, panel centre ``height_m`` high (a moved sign
    keeps its own), facing the traffic of its edge +- ``facing_jitter_deg``, a share
    ``along`` of its edge's length (edges drawn in proportion to length), ``kerb_m`` from
    every road centreline, ``clear_m`` from every other sign that ever stands (the first
    fit of ``draws`` candidates). A moved sign goes ``move_m`` (horizontally) along a road
    of its traffic's direction; a temporary one stands ``window_share`` of the span."""

    lateral_m: tuple[float, float] = (2.5, 4.0)
    height_m: tuple[float, float] = (2.0, 2.8)
    facing_jitter_deg: float = 8.0
    along: tuple[float, float] = (0.12, 0.88)
    kerb_m: float = 3.5
    clear_m: float = 12.0
    move_m: tuple[float, float] = (5.0, 30.0)
    window_share: tuple[float, float] = (0.2, 0.5)
    draws: int = 256


PLACEMENT = Placement()


def _place(
    world: World,
    rng: Generator,
    edge: NDArray,
    s: Array,
    placed: Array,
    pl: Placement,
    moved_from: Array | None = None,
) -> tuple[Array, float] | None:
    """The first of the points ``s`` m along directed edges (rows of ``world.edges``),
    beside the road, that is on its edge, clear of the roads and of ``placed`` (and
    ``pl.move_m`` from ``moved_from``): (xy, facing deg); None if none is."""
    e, lateral = world.edges[edge], rng.uniform(*pl.lateral_m, len(edge))
    length = np.linalg.norm(world.nodes[e[:, 1]] - world.nodes[e[:, 0]], axis=1)
    xy, az = roadside(world.nodes, e, s / length, lateral, world.lane_offset_m)
    az = az + rng.uniform(-pl.facing_jitter_deg, pl.facing_jitter_deg, len(edge))
    a, b = world.nodes[world.edges[:, 0]], world.nodes[world.edges[:, 1]]
    ok = (s >= 0.0) & (s <= length) & (segment_distance(xy, a, b) >= pl.kerb_m)
    if len(placed):
        ok &= np.linalg.norm(xy[:, None] - placed[None], axis=-1).min(axis=1) >= pl.clear_m
    if moved_from is not None:
        moved = np.linalg.norm(xy - moved_from, axis=1)
        ok &= (moved >= pl.move_m[0]) & (moved <= pl.move_m[1])
    i = np.flatnonzero(ok)
    return (xy[i[0]], float(az[i[0]])) if i.size else None


def _move_to(
    world: World, rng: Generator, sign: Signs, placed: Array, pl: Placement
) -> tuple[Array, float] | None:
    """A new place (xy, facing deg) for ``sign`` ``pl.move_m`` away, beside an edge of its
    traffic's direction (within 30 deg); None if no draw fits."""
    p, d = sign.position[0, :2], -sign.facing[0, :2] / np.linalg.norm(sign.facing[0, :2])
    a, b = world.nodes[world.edges[:, 0]], world.nodes[world.edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    t = (b - a) / np.maximum(length, 1e-9)[:, None]
    foot = np.clip(np.sum((p - a) * t, axis=1), 0.0, length)
    dist = np.linalg.norm(a + t * foot[:, None] - p, axis=1)
    near = np.flatnonzero((t @ d >= np.cos(np.radians(30.0))) & (dist <= 2 * pl.move_m[1]))
    if not near.size:
        return None
    k = near[rng.integers(near.size, size=pl.draws)]
    s = foot[k] + rng.uniform(-pl.move_m[1], pl.move_m[1], pl.draws)
    return _place(world, rng, k, s, placed, pl, p)


def random_schedule(
    world: World,
    rng: Generator,
    t0: float,
    t1: float,
    n_remove: int = 0,
    n_move: int = 0,
    n_replace: int = 0,
    n_add: int = 0,
    n_temporary: int = 0,
    *,
    codes: ArrayLike | None = None,
    placement: Placement = PLACEMENT,
) -> ChangeSchedule:
    """A plausible schedule of changes to ``world``'s signs at uniform times in [t0, t1]
    (in time order): distinct signs taken down, moved (:class:`Placement`) and replaced by
    another class of ``codes`` (None: the world's classes, or the catalogue's if it has
    one); new and temporary signs of ``codes`` placed as the world's own. Deterministic
    for ``rng``'s state; ValueError when the world lacks room."""
    signs, pl, n_new = world.signs, placement, n_add + n_temporary
    if not t0 <= t1 or n_remove + n_move + n_replace > len(signs) or not len(world.edges):
        raise ValueError("need t0 <= t1, roads, and no more changed signs than the world has")
    cls = np.unique(signs.sign_class) if codes is None else np.asarray(codes, np.int64)
    cls = CATALOG.codes if cls.size < 2 and codes is None else cls
    placed, moves, rest, new = signs.position[:, :2], [], [], []
    for r in rng.permutation(len(signs)).tolist():
        got = None
        if len(moves) < n_move:
            got = _move_to(world, rng, signs.take([r]), np.delete(placed, r, axis=0), pl)
        if got is None:
            rest.append(r)
        else:
            moves.append((r, *got))
            placed = np.vstack([placed, got[0]])
    length = np.linalg.norm(np.diff(world.nodes[world.edges], axis=1), axis=-1)[:, 0]
    while len(new) < n_new:
        k = rng.choice(len(world.edges), pl.draws, p=length / length.sum())
        got = _place(world, rng, k, length[k] * rng.uniform(*pl.along, pl.draws), placed, pl)
        if got is None:
            raise ValueError(f"room to put up only {len(new)} of {n_new} signs")
        new.append(got)
        placed = np.vstack([placed, got[0]])
    if len(moves) < n_move:
        raise ValueError(f"room to move only {len(moves)} of {n_move} signs")

    ids, sch = signs.id.tolist(), ChangeSchedule()
    for r in rest[:n_remove]:
        sch = sch.with_removal(signs, ids[r], rng.uniform(t0, t1))
    for r, xy, az in moves:
        sch = sch.with_move(signs, ids[r], rng.uniform(t0, t1), xy - signs.position[r, :2], az)
    for r in rest[n_remove : n_remove + n_replace]:
        other = cls[cls != signs.sign_class[r]]
        if not other.size:
            raise ValueError(f"no class other than sign {ids[r]}'s among {cls.tolist()}")
        sch = sch.with_replacement(signs, ids[r], rng.uniform(t0, t1), int(rng.choice(other)))
    for j, (xy, az) in enumerate(new):
        sign = Signs.build([rng.choice(cls)], [[*xy, rng.uniform(*pl.height_m)]], [az])
        w = (t1 - t0) * rng.uniform(*pl.window_share) if j >= n_add else None
        ta = rng.uniform(t0, t1) if w is None else rng.uniform(t0, t1 - w)
        sch = sch.with_addition(signs, ta, sign, None if w is None else ta + max(w, 1e-6))
    return replace(sch, changes=tuple(sorted(sch.changes, key=lambda c: c.t)))
