"""Admission policy beyond the wire schema: what ingest refuses even if well-formed.

>>> import numpy as np
>>> from schemas import Observations
>>> obs = Observations.empty()
>>> admit(obs, AdmissionPolicy(), now=1.7e9, tiles=np.zeros(0, str))[1]
[]
>>> check_header(ObservationBatch("veh-1", 2**63, 1, 1.7e9, obs))
Traceback (most recent call last):
...
schemas.codec.DecodeError: pass_id: 9223372036854775808 is above 9223372036854775807 ...
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas import Absences, DecodeError, ObservationBatch, Observations, Rejection

MAX_PASS_ID = 2**63 - 1
"""Largest pass id ingest accepts: downstream (the matcher's pending rays) keeps pass ids
as signed 64-bit integers, so a larger one would be acknowledged, then lost."""


def check_header(batch: ObservationBatch) -> None:
    """Refuse a whole batch whose header the pipeline cannot carry (``DecodeError``)."""
    if batch.pass_id > MAX_PASS_ID:
        raise DecodeError(
            "pass_id", f"{batch.pass_id} is above {MAX_PASS_ID} (pass ids are signed 64-bit)"
        )


@dataclass(frozen=True)
class AdmissionPolicy:
    max_age_s: float = 30 * 24 * 3600.0
    """Observations older than this (capture time vs arrival) are refused."""
    max_future_s: float = 300.0
    """Clock skew tolerated for capture times ahead of the ingest clock."""
    max_lag_s: float | None = None
    """Observations captured more than this before the newest capture time ingest has
    admitted (the fleet's own clock: :attr:`IngestService.horizon`) are refused; None:
    ``max_age_s``. Ingest forgets the ids of what this refuses (its dedup table holds this
    much of the fleet's time), so a smaller lag bounds that table where the fleet's time
    runs ahead of the wall clock (a replay, an accelerated soak) at the cost of refusing
    uploads later than it."""
    min_score: float = 0.0
    """Detections below this detector score are refused."""
    max_per_image: int = 64
    """Detections of one image beyond this many (in batch order) are refused: a camera
    frame does not hold hundreds of signs, and the matcher's initiation is quadratic in
    the rays of one pass (3,000 rays of one image kept it busy 17 s)."""
    max_tiles: int = 32
    """Rows in tiles beyond the first this many an upload touches (in batch order) are
    refused: each tile costs a log entry and a matcher transaction step whatever it holds,
    so one vehicle spreading 10,000 observations over the globe held up everyone's uploads
    (honest p99 3.4 s -> 114 s, ``benchmarks/bench_hostile.py``). One pass's batch of 500
    observations (the uploader's batch) covers well under a kilometre of road: a few
    tiles of zoom 16; a refused row can be sent again in another batch."""


def admit(
    obs: Observations,
    policy: AdmissionPolicy,
    now: float,
    tiles: np.ndarray,
    horizon: float = -np.inf,
) -> tuple[np.ndarray, list[Rejection]]:
    """Which schema-valid observations are admitted (a mask; ``tiles``: each row's tile),
    and the rejections of the others with reasons (``horizon``: the newest capture time
    admitted before)."""
    too_old = obs.t < oldest_admitted(policy, now, horizon)
    future = obs.t > now + policy.max_future_s
    low = (obs.score < policy.min_score) & ~too_old & ~future
    crowded = _beyond_per_image(obs.image, policy.max_per_image) & ~too_old & ~future & ~low
    bad = too_old | future | low | crowded
    spread = np.zeros(len(obs), bool)
    spread[~bad] = _beyond_first_tiles(np.asarray(tiles)[~bad], policy.max_tiles)
    bad |= spread
    if not bad.any():
        return ~bad, []
    rejected: list[Rejection] = []
    for mask, field, reason in (
        (
            too_old,
            "obs.t",
            f"older than {policy.max_age_s:g} s or than the fleet's "
            f"newest observation by {lag_s(policy):g} s",
        ),
        (future, "obs.t", f"more than {policy.max_future_s:g} s in the future"),
        (low, "obs.score", f"below the minimum score {policy.min_score:g}"),
        (crowded, "obs.image", f"more than {policy.max_per_image} detections in one image"),
        (spread, "obs.lat", f"in a tile beyond the first {policy.max_tiles} of this upload"),
    ):
        rejected += [Rejection(int(i), field, reason) for i in obs.obs_id[mask]]
    return ~bad, rejected


def admit_absences(
    ab: Absences, policy: AdmissionPolicy, now: float, tiles: np.ndarray, horizon: float
) -> tuple[np.ndarray, list[Rejection]]:
    """Which schema-valid absences are admitted (the observations' time window; at most
    ``policy.max_tiles`` home tiles an upload), with the rejections of the others (the
    landmark id in ``obs_id``)."""
    too_old = ab.t < oldest_admitted(policy, now, horizon)
    future = ab.t > now + policy.max_future_s
    bad = too_old | future
    spread = np.zeros(len(ab), bool)
    spread[~bad] = _beyond_first_tiles(np.asarray(tiles)[~bad], policy.max_tiles)
    bad |= spread
    rejected: list[Rejection] = []
    for mask, field, reason in (
        (too_old, "absences.t", f"older than the admission window ({lag_s(policy):g} s)"),
        (future, "absences.t", f"more than {policy.max_future_s:g} s in the future"),
        (
            spread,
            "absences.landmark_id",
            f"in a home tile beyond the first {policy.max_tiles} of this upload",
        ),
    ):
        rejected += [Rejection(int(i), field, reason) for i in ab.landmark_id[mask]]
    return ~bad, rejected


def lag_s(policy: AdmissionPolicy) -> float:
    """How far behind the newest capture time an observation may be."""
    return policy.max_age_s if policy.max_lag_s is None else policy.max_lag_s


def oldest_admitted(policy: AdmissionPolicy, now: float, horizon: float) -> float:
    """The oldest capture time admitted at wall time ``now`` after the newest admitted
    ``horizon``: older ones are refused, so their ids need not be remembered.

    >>> oldest_admitted(AdmissionPolicy(max_age_s=100.0, max_lag_s=10.0), 1000.0, 995.0)
    985.0
    """
    return max(now - policy.max_age_s, horizon - lag_s(policy))


def _beyond_first_tiles(tiles: np.ndarray, limit: int) -> np.ndarray:
    """Rows whose tile is not among the first ``limit`` distinct tiles (by first row).

    >>> _beyond_first_tiles(np.array(["a", "b", "a", "c", "b"]), 2).tolist()
    [False, False, False, True, False]
    """
    if tiles.size == 0:
        return np.zeros(0, bool)
    uniq, first, inv = np.unique(tiles, return_index=True, return_inverse=True)
    if uniq.size <= limit:
        return np.zeros(tiles.size, bool)
    rank = np.empty(uniq.size, np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(uniq.size)
    return rank[inv] >= limit


def _beyond_per_image(image: np.ndarray, limit: int) -> np.ndarray:
    """Rows past the first ``limit`` of their image (in order).

    >>> _beyond_per_image(np.array([3, 3, 3, 5, 3]), 2).tolist()
    [False, False, True, False, True]
    """
    image = np.asarray(image)
    if image.size <= limit:
        return np.zeros(image.size, bool)
    order = np.argsort(image, kind="stable")
    s = image[order]
    start = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1]
    rank = np.arange(s.size) - np.repeat(start, np.diff(np.r_[start, s.size]))
    out = np.zeros(image.size, bool)
    out[order] = rank >= limit
    return out
