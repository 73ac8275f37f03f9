"""Wire schemas (version 1) and the codec that validates them at the boundary.

See ``schemas/README.md`` for every message, field by field. The messages live by concern
in :mod:`schemas.upload`, :mod:`schemas.logs`, :mod:`schemas.map`, :mod:`schemas.control`
and :mod:`schemas.handover` (on the shared base :mod:`schemas.messages`), the tables they carry
in :mod:`schemas.tables`; every name is importable from here.
"""

from schemas.codec import VERSION, DecodeError
from schemas.control import ErrorReply, Stats
from schemas.handover import HandoverReply, HandoverRequest
from schemas.logs import (
    AssocGroup,
    LandmarkUpdates,
    LogEntry,
    LogHead,
    LogMark,
    LogQuery,
    ObsGroup,
    decode_replay,
)
from schemas.map import MapDelta, MapSnapshot
from schemas.messages import MAX_BATCH
from schemas.tables import (
    DROP,
    RELEASE,
    STATUS_CANDIDATE,
    STATUS_CONFIRMED,
    STATUS_RETIRED,
    Absences,
    ExistenceRows,
    Landmarks,
    Links,
    NewLandmarks,
    Observations,
    Removals,
    TrustChanges,
)
from schemas.upload import ObservationBatch, Rejection, UploadAck

__all__ = [
    "DROP",
    "MAX_BATCH",
    "RELEASE",
    "STATUS_CANDIDATE",
    "STATUS_CONFIRMED",
    "STATUS_RETIRED",
    "VERSION",
    "Absences",
    "AssocGroup",
    "DecodeError",
    "ErrorReply",
    "ExistenceRows",
    "HandoverReply",
    "HandoverRequest",
    "LandmarkUpdates",
    "Landmarks",
    "Links",
    "LogEntry",
    "LogHead",
    "LogMark",
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
    "TrustChanges",
    "UploadAck",
    "decode_replay",
]
