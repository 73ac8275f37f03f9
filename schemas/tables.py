"""The columnar tables the messages carry (``schemas/README.md``, "Tables"), with the
codes of their enumerated columns.

>>> len(Removals.empty()), STATUS_CONFIRMED, RELEASE
(0, 1, 1)
"""

from __future__ import annotations

import math

import numpy as np

from schemas.codec import Table, col, table
from schemas.messages import FLOAT_EPOCH_MAX


@table
class Observations(Table):
    """Projection lines, one row per detection (see geoloc.ProjectionLines)."""

    obs_id: np.ndarray = col("u8", doc="unique per vehicle")
    t: np.ndarray = col("f8", lo=0.0, hi=FLOAT_EPOCH_MAX, unit_label="s", doc="capture time, Unix")
    image: np.ndarray = col("u4", doc="image index within the pass; same value = same image")
    sign_class: np.ndarray = col("u2", doc="sign class code (hdmap.geo.signs)")
    lat: np.ndarray = col("f8", lo=-90.0, hi=90.0, unit_label="deg", doc="camera centre A")
    lon: np.ndarray = col("f8", lo=-180.0, hi=180.0, unit_label="deg")
    h: np.ndarray = col("f8", lo=-1000.0, hi=10000.0, unit_label="m", doc="ellipsoidal height")
    direction: np.ndarray = col("f8", 3, unit=True, doc="unit vector, ENU at A")
    sigma_az: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=math.pi, unit_label="rad")
    sigma_el: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=math.pi, unit_label="rad")
    sigma_pos_h: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=1000.0, unit_label="m")
    sigma_pos_v: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=1000.0, unit_label="m")
    range_m: np.ndarray = col("f8", lo=0.0, hi=10000.0, unit_label="m", doc="0 = no estimate")
    sigma_range_m: np.ndarray = col("f8", lo=0.0, hi=10000.0, unit_label="m")
    score: np.ndarray = col("f4", lo=0.0, hi=1.0)
    track: np.ndarray = col(
        "u4",
        optional=True,
        doc="detections of one sign followed from image to image within the pass; 0 = none",
    )


@table
class Absences(Table):
    """Mapped landmarks a pass had in view and did not detect (issue 21's negative
    evidence; :mod:`vehicle.absence`), one row per landmark per pass."""

    landmark_id: np.ndarray = col("u8", doc="the published id the vehicle expected to see")
    t: np.ndarray = col(
        "f8", lo=0.0, hi=FLOAT_EPOCH_MAX, unit_label="s", doc="capture time of the closest view"
    )
    frames: np.ndarray = col("u4", lo=1, hi=100_000, doc="frames of the pass that had it in view")
    share: np.ndarray = col("f4", lo=0.0, hi=1.0, doc="those frames' share of the pass's frames")
    range_m: np.ndarray = col(
        "f4", lo=0.0, hi=1000.0, unit_label="m", doc="horizontal range at the closest view"
    )
    bearing_deg: np.ndarray = col(
        "f4",
        lo=-180.0,
        hi=180.0,
        unit_label="deg",
        doc="bearing from the camera's axis at the closest view, clockwise",
    )


@table
class Links(Table):
    """Per associated observation: its landmark and where it came from."""

    landmark_id: np.ndarray = col("u8")
    vehicle: np.ndarray = col("u4", doc="index into AssocGroup.vehicles")
    pass_id: np.ndarray = col("u8")
    received_at: np.ndarray = col(
        "f8", lo=0.0, hi=FLOAT_EPOCH_MAX, unit_label="s", doc="ingest receipt time, Unix"
    )
    weight: np.ndarray = col(
        "f4", lo=0.0, hi=1.0, doc="relative weight of the observation (trust in its vehicle)"
    )


@table
class TrustChanges(Table):
    """A vehicle leaves probation: its held passes (links with ``held``) are let go at a new
    weight (``action`` 1: promoted) or taken out (``action`` 2: caught shifting its data)."""

    vehicle: np.ndarray = col("u4", doc="index into AssocGroup.vehicles")
    action: np.ndarray = col("u1", lo=1, hi=2, doc="1 = release (promoted), 2 = drop (caught)")
    weight: np.ndarray = col("f4", lo=0.0, hi=1.0, doc="weight of the released rays")


RELEASE, DROP = 1, 2
"""``TrustChanges.action`` values."""


@table
class NewLandmarks(Table):
    """Landmarks created by the matcher, with the triangulated initial position."""

    id: np.ndarray = col("u8")
    sign_class: np.ndarray = col("u2")
    lat: np.ndarray = col("f8", lo=-90.0, hi=90.0, unit_label="deg")
    lon: np.ndarray = col("f8", lo=-180.0, hi=180.0, unit_label="deg")
    h: np.ndarray = col("f8", lo=-1000.0, hi=10000.0, unit_label="m")


@table
class ExistenceRows(Table):
    """Matcher -> solver: landmarks whose existence changed (:mod:`hdmap.mapping.existence`)."""

    landmark_id: np.ndarray = col("u8")
    p_exist: np.ndarray = col("f4", lo=0.0, hi=1.0, doc="probability that the sign stands")
    state: np.ndarray = col("u1", lo=1, hi=2, doc="1 confirmed, 2 doubtful (revoked: retired)")
    first_seen: np.ndarray = col(
        "f8", lo=0.0, hi=FLOAT_EPOCH_MAX, unit_label="s", doc="event time of its first ray"
    )
    last_seen: np.ndarray = col(
        "f8", lo=0.0, hi=FLOAT_EPOCH_MAX, unit_label="s", doc="event time of its latest ray"
    )


EXIST_UNKNOWN, EXIST_CONFIRMED, EXIST_DOUBTFUL = 0, 1, 2
"""``ExistenceRows.state`` and ``MapLandmarks.exist_state`` values (0: not known, an older
sender)."""


@table
class Landmarks(Table):
    """Landmark estimates as published (update, delta, snapshot)."""

    id: np.ndarray = col("u8")
    sign_class: np.ndarray = col("u2")
    lat: np.ndarray = col("f8", lo=-90.0, hi=90.0, unit_label="deg")
    lon: np.ndarray = col("f8", lo=-180.0, hi=180.0, unit_label="deg")
    h: np.ndarray = col("f8", lo=-1000.0, hi=10000.0, unit_label="m")
    cov: np.ndarray = col("f8", 6, unit_label="m^2", doc="ENU at the landmark: ee en eu nn nu uu")
    status: np.ndarray = col("u1", lo=0, hi=2, doc="0 candidate, 1 confirmed (located), 2 retired")
    n_obs: np.ndarray = col("u4")
    n_passes: np.ndarray = col("u4")
    revision: np.ndarray = col("u8", doc="grows with every change of this landmark")
    updated_at: np.ndarray = col("f8", lo=0.0, hi=FLOAT_EPOCH_MAX, unit_label="s")
    source_time: np.ndarray = col(
        "f8",
        lo=0.0,
        hi=FLOAT_EPOCH_MAX,
        unit_label="s",
        doc="ingest receipt time of the newest observation in this revision (latency tracing)",
    )


@table
class Removals(Table):
    id: np.ndarray = col("u8")
    revision: np.ndarray = col("u8")


STATUS_CANDIDATE, STATUS_CONFIRMED, STATUS_RETIRED = 0, 1, 2
