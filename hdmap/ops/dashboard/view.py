"""The dashboard's memory of the map: current features, what changed, each landmark's history.

:meth:`MapView.update` takes the whole map as held now (the map client's landmarks) and
returns what changed since the last call: the features of the landmarks that are new or
have a new ``revision``, and the ids that left (removed by the publisher, or moved out of
the area). Each change is one entry of the landmark's history: what the dashboard has
seen of it, one entry per revision seen (revisions between two updates are not seen),
and a ``removed`` entry when it leaves. The history is bounded: ``history_len`` entries
per landmark, ``history_landmarks`` landmarks (the least recently changed forgotten
first, removed or not). Thread-safe (one lock); no I/O.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdmap.ops.dashboard.geometry import STATUSES, feature_collection, landmark_features
from schemas.map import MapLandmarks

HISTORY_FIELDS = (
    "revision",
    "updated_at",
    "lat",
    "lon",
    "h",
    "sigma_e_m",
    "sigma_n_m",
    "sigma_u_m",
    "ellipse_major_m",
    "ellipse_minor_m",
    "passes",
    "n_obs",
    "status",
    "p_exist",
    "facing_deg",
    "facing_sigma_deg",
)
"""The properties a history entry keeps (with ``seen_at``, when the dashboard saw it)."""


@dataclass
class Change:
    """What one :meth:`MapView.update` changed (empty: nothing)."""

    upserts: list[dict[str, Any]] = field(default_factory=list)
    """Every feature of each new or changed landmark (its old ones are replaced)."""
    removed: list[str] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.upserts or self.removed)

    def to_json(self) -> dict[str, Any]:
        return {"upserts": self.upserts, "removed": self.removed}


def latest_per_id(lm: MapLandmarks) -> MapLandmarks:
    """One row per id, the highest revision (a landmark moving between two tiles can be
    in both copies for a moment)."""
    if len(lm) == 0:
        return lm
    order = np.lexsort((-lm.revision.astype(np.float64), lm.id))
    ids = lm.id[order]
    first = np.ones(len(ids), bool)
    first[1:] = ids[1:] != ids[:-1]
    return lm.take(order[first])


class MapView:
    def __init__(
        self, history_len: int = 50, history_landmarks: int = 20_000, arrow_m: float = 8.0
    ):
        if history_len < 1 or history_landmarks < 1:
            raise ValueError("history_len and history_landmarks must be >= 1")
        self.history_len = history_len
        self.history_landmarks = history_landmarks
        self.arrow_m = arrow_m
        self._lock = threading.Lock()
        self._revisions: dict[str, int] = {}
        self._features: dict[str, list[dict[str, Any]]] = {}
        self._history: OrderedDict[str, deque[dict[str, Any]]] = OrderedDict()
        self.updates = 0
        """Calls of :meth:`update` that changed something."""

    def update(self, lm: MapLandmarks, now: float) -> Change:
        """Take the map as held now (wall time ``now``); what changed."""
        lm = latest_per_id(lm)
        ids = [str(int(i)) for i in lm.id]
        with self._lock:
            changed = [
                k for k, i in enumerate(ids) if self._revisions.get(i) != int(lm.revision[k])
            ]
            gone = sorted(set(self._revisions) - set(ids))
        feats = landmark_features(lm.take(np.array(changed, np.int64)), self.arrow_m)
        change = Change(removed=gone)
        with self._lock:
            for i, fs in feats.items():
                point = fs[0]["properties"]
                self._revisions[i] = point["revision"]
                self._features[i] = fs
                change.upserts.extend(fs)
                entry = {k: point.get(k) for k in HISTORY_FIELDS}
                self._remember(i, {"seen_at": round(now, 3), **entry})
            for i in gone:
                last = self._revisions.pop(i)
                self._features.pop(i, None)
                self._remember(i, {"seen_at": round(now, 3), "revision": last, "removed": True})
            if change:
                self.updates += 1
        return change

    def _remember(self, lid: str, entry: dict[str, Any]) -> None:
        h = self._history.get(lid)
        if h is None:
            h = self._history[lid] = deque(maxlen=self.history_len)
        self._history.move_to_end(lid)
        h.append(entry)
        while len(self._history) > self.history_landmarks:
            self._history.popitem(last=False)

    def history(self, lid: str) -> list[dict[str, Any]] | None:
        """The entries seen of one landmark, oldest first (None: never seen, or forgotten)."""
        with self._lock:
            h = self._history.get(lid)
            return None if h is None else list(h)

    def collection(self) -> dict[str, Any]:
        """Every current feature as one GeoJSON FeatureCollection."""
        with self._lock:
            return feature_collection([f for fs in self._features.values() for f in fs])

    def counts(self) -> dict[str, int]:
        """Landmarks per display status (every status, 0 included)."""
        with self._lock:
            c = Counter(fs[0]["properties"]["status"] for fs in self._features.values())
        return {s: c.get(s, 0) for s in STATUSES}

    def __len__(self) -> int:
        with self._lock:
            return len(self._features)
