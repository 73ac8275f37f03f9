"""A tile's pending pool: the rays routed to one tile that wait for a landmark, as columns
(:class:`PendingTile`; the matcher's :class:`~hdmap.mapping.landmarks.LandmarkTable`
keeps one per tile)."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.ids import pass_key


class _Column:
    """A column of :class:`PendingTile` (stored as ``_<name>``), read once the queued rows
    are concatenated onto it; ``writable``: assignable too (as a bool array)."""

    def __init__(self, writable: bool = False) -> None:
        self.writable = writable

    def __set_name__(self, owner: type, name: str) -> None:
        self.attr = f"_{name}"

    def __get__(self, obj: PendingTile | None, owner: type | None = None) -> Any:
        if obj is None:
            return self
        return getattr(obj._columns(), self.attr)

    def __set__(self, obj: PendingTile, value: Any) -> None:
        if not self.writable:
            raise AttributeError(f"{self.attr[1:]} is read only")
        setattr(obj._columns(), self.attr, np.asarray(value, bool))


class PendingTile:
    """Rays routed to one tile that wait for a landmark (columnar).

    Columns: ``obs`` (the rays, an :class:`~hdmap.mapping.landmarks.ObsRows` table),
    ``vehicle`` (an object array of vehicle ids), ``pass_id``, ``added_at`` (event time the
    pending TTL is counted from), ``received_at`` (ingest receipt, latency tracing), ``key``
    (:func:`pass_key` of each ray's (vehicle, pass): vectorised selection of a pass),
    ``tried`` (the ray has been a seed of an initiation attempt,
    :func:`hdmap.mapping.pending.initiate`; every ray is offered as a seed in the unit that
    pools it or at the end of its gating tick, and rows given without it are tried: a store
    passes the untried ones of the current tick) and ``saved`` (the ray is in storage; rows
    given without it: saved).

    Appending is O(rows appended): :meth:`add` queues its rows, and the columns are
    concatenated once, when one is next read (a gating tick's uploads add to a tile's pool
    many times before its end reads it). The rays each vehicle and each pass have here are
    counted as they come and go (:meth:`count_of`, ``per_vehicle``), so a budget check
    reads no column. Invariant: the rows read are the rows added, in the order added, less
    those :meth:`keep` dropped."""

    def __init__(
        self,
        obs: Any,
        vehicle: list[str] | NDArray[Any] | None = None,
        pass_id: NDArray[np.int64] | None = None,
        added_at: NDArray[np.float64] | None = None,
        received_at: NDArray[np.float64] | None = None,
    ) -> None:
        n = len(obs)
        self._obs = obs
        self._vehicle = np.array(list(vehicle) if vehicle is not None else [], dtype=object)
        self._pass_id = np.zeros(0, np.int64) if pass_id is None else np.asarray(pass_id, np.int64)
        self._added_at = np.zeros(0) if added_at is None else np.asarray(added_at, float)
        self._received_at = np.zeros(0) if received_at is None else np.asarray(received_at, float)
        self._key = np.array(
            [pass_key(str(v), int(p)) for v, p in zip(self._vehicle, self._pass_id, strict=True)],
            np.int64,
        )
        self._tried = np.ones(n, bool)
        self._saved = np.ones(n, bool)
        self._local = np.full((n, 6), np.nan)
        self._tail: list[tuple[Any, str, int, NDArray[np.float64], float, int, Any]] = []
        self._n = n
        self.per_vehicle: Counter[str] = Counter(self._vehicle.tolist())
        """Rays of each vehicle (the per-vehicle budget is checked at every upload)."""
        self._per_key: Counter[int] = Counter(self._key.tolist())

    def __len__(self) -> int:
        return self._n

    def count_of(self, key: int) -> int:
        """Rays of the pass with :func:`pass_key` ``key`` here."""
        return self._per_key[key]

    def add(
        self,
        obs: Any,
        vehicle: str,
        pass_id: int,
        at: float | NDArray[np.float64],
        received: float,
        local: NDArray[np.float64] | None = None,
    ) -> None:
        """Append one pass's rays with their event times ``at`` (one per ray, or one for
        all: what the pending TTL is counted from), received by ingest at ``received``;
        ``local``: their origins and directions in the tile's frame, (n, 6), if known."""
        n = len(obs)
        if not n:
            return
        key = pass_key(vehicle, pass_id)
        at_rows = np.array(np.broadcast_to(np.asarray(at, float), n))
        self._tail.append((obs, vehicle, pass_id, at_rows, received, key, local))
        self._n += n
        self.per_vehicle[vehicle] += n
        self._per_key[key] += n

    def _flush(self) -> None:
        """Concatenate the queued rows onto the columns (once for all of them)."""
        tail, self._tail = self._tail, []
        sizes = [len(t[0]) for t in tail]

        def per_row(i: int, dtype: Any) -> NDArray[Any]:
            """Field ``i`` of each queued pass, repeated for each of its rows."""
            return np.repeat(np.array([t[i] for t in tail], dtype=dtype), sizes)

        self._obs = type(tail[0][0]).concat([self._obs, *(t[0] for t in tail)])
        self._vehicle = np.concatenate([self._vehicle, per_row(1, object)])
        self._pass_id = np.concatenate([self._pass_id, per_row(2, np.int64)])
        self._added_at = np.concatenate([self._added_at, *(t[3] for t in tail)])
        self._received_at = np.concatenate([self._received_at, per_row(4, float)])
        self._key = np.concatenate([self._key, per_row(5, np.int64)])
        local = [
            np.full((k, 6), np.nan) if t[6] is None else t[6]
            for t, k in zip(tail, sizes, strict=True)
        ]
        self._local = np.concatenate([self._local, *local])
        total = sum(sizes)
        self._tried = np.concatenate([self._tried, np.zeros(total, bool)])
        self._saved = np.concatenate([self._saved, np.zeros(total, bool)])

    def _columns(self) -> PendingTile:
        if self._tail:
            self._flush()
        return self

    obs = _Column()
    vehicle = _Column()
    pass_id = _Column()
    added_at = _Column()
    received_at = _Column()
    key = _Column()
    tried = _Column(writable=True)
    saved = _Column()
    local = _Column()
    """(n, 6): each ray's origin and direction in the tile's frame, NaN where not computed
    yet (:func:`hdmap.mapping.pending.pool_rays` fills it in: a conversion's rows do not
    depend on the rows converted with them, so a kept row is the one a conversion anew
    gives)."""

    def keep(self, mask: NDArray[np.bool_]) -> None:
        """Keep only the rows ``mask`` marks."""
        self._columns()
        gone = ~mask
        if gone.any():
            v, k = np.unique(self._vehicle[gone], return_counts=True)
            self.per_vehicle.subtract(dict(zip(v.tolist(), k.tolist(), strict=True)))
            self.per_vehicle = +self.per_vehicle  # vehicles without rays go
            p, k = np.unique(self._key[gone], return_counts=True)
            self._per_key.subtract(dict(zip(p.tolist(), k.tolist(), strict=True)))
            self._per_key = +self._per_key
        self._obs = self._obs.take(mask)
        self._vehicle = self._vehicle[mask]
        self._pass_id = self._pass_id[mask]
        self._added_at = self._added_at[mask]
        self._received_at = self._received_at[mask]
        self._key = self._key[mask]
        self._local = self._local[mask]
        self._tried = self._tried[mask]
        self._saved = self._saved[mask]
        self._n = int(mask.sum())
