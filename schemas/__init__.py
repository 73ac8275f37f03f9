"""Wire schemas (version 1) and the codec that validates them at the boundary.

See ``schemas/README.md`` for every message, field by field.
"""

from schemas.codec import VERSION, DecodeError
from schemas.messages import (
    MAX_BATCH,
    STATUS_CANDIDATE,
    STATUS_CONFIRMED,
    STATUS_RETIRED,
    AssocGroup,
    ErrorReply,
    Landmarks,
    LandmarkUpdates,
    Links,
    LogEntry,
    LogQuery,
    MapDelta,
    MapSnapshot,
    NewLandmarks,
    ObservationBatch,
    Observations,
    ObsGroup,
    Rejection,
    Removals,
    Stats,
    UploadAck,
)

__all__ = [
    "MAX_BATCH",
    "STATUS_CANDIDATE",
    "STATUS_CONFIRMED",
    "STATUS_RETIRED",
    "VERSION",
    "AssocGroup",
    "DecodeError",
    "ErrorReply",
    "LandmarkUpdates",
    "Landmarks",
    "Links",
    "LogEntry",
    "LogQuery",
    "MapDelta",
    "MapSnapshot",
    "NewLandmarks",
    "ObsGroup",
    "ObservationBatch",
    "Observations",
    "Rejection",
    "Removals",
    "Stats",
    "UploadAck",
]
