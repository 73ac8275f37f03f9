"""Admission policy beyond the wire schema: what ingest refuses even if well-formed.

>>> import numpy as np
>>> from schemas import Observations
>>> obs = Observations.empty()
>>> admit(obs, AdmissionPolicy(), now=1.7e9)[1]
[]
>>> check_header(ObservationBatch("veh-1", 2**63, 1, 1.7e9, obs))
Traceback (most recent call last):
...
schemas.codec.DecodeError: pass_id: 9223372036854775808 is above 9223372036854775807 ...
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas import DecodeError, ObservationBatch, Observations, Rejection

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
    min_score: float = 0.0
    """Detections below this detector score are refused."""
    max_per_image: int = 64
    """Detections of one image beyond this many (in batch order) are refused: a camera
    frame does not hold hundreds of signs, and the matcher's initiation is quadratic in
    the rays of one pass (3,000 rays of one image kept it busy 17 s)."""


def admit(
    obs: Observations, policy: AdmissionPolicy, now: float
) -> tuple[Observations, list[Rejection]]:
    """Split schema-valid observations into admitted ones and rejections with reasons."""
    too_old = obs.t < now - policy.max_age_s
    future = obs.t > now + policy.max_future_s
    low = (obs.score < policy.min_score) & ~too_old & ~future
    crowded = _beyond_per_image(obs.image, policy.max_per_image) & ~too_old & ~future & ~low
    bad = too_old | future | low | crowded
    if not bad.any():
        return obs, []
    rejected: list[Rejection] = []
    for mask, field, reason in (
        (too_old, "obs.t", f"older than {policy.max_age_s:g} s"),
        (future, "obs.t", f"more than {policy.max_future_s:g} s in the future"),
        (low, "obs.score", f"below the minimum score {policy.min_score:g}"),
        (crowded, "obs.image", f"more than {policy.max_per_image} detections in one image"),
    ):
        rejected += [Rejection(int(i), field, reason) for i in obs.obs_id[mask]]
    return obs.take(~bad), rejected


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
