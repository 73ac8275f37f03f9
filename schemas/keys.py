"""Every Zenoh key expression of the system, in one place (see schemas/README.md).

``<tile>`` is one quadkey chunk; a region is a quadkey prefix selected with the
sub-chunk wildcard ``$*`` (``hdmap/v1/obs/120210$*`` matches every tile under
``120210``).

A map snapshot is asked for on one of two keys: ``hdmap/v1/map/<tile>`` (anonymous:
operators, tools, older vehicles) or ``hdmap/v1/map/<tile>/by/<client>``
(:func:`map_snapshot_for`), which names the client the publisher limits the query under.
In secured mode the router lets a vehicle query only the keys ending in its own
authenticated id, so there ``<client>`` is the vehicle's identity; the anonymous queries
share one budget (:data:`ANONYMOUS`).

>>> obs('1202')
'hdmap/v1/obs/1202'
>>> obs(region('120'))
'hdmap/v1/obs/120$*'
>>> obs(region(''))
'hdmap/v1/obs/*'
"""

from __future__ import annotations

from schemas.codec import valid_id

ROOT = "hdmap/v1"
ANY = "*"
ANONYMOUS = "anonymous"
"""The client every anonymous snapshot query (``hdmap/v1/map/<tile>``) counts as."""


def region(prefix: str) -> str:
    """Chunk selecting every tile under a quadkey prefix ('' = every tile)."""
    return f"{prefix}$*" if prefix else ANY


def upload(vehicle_id: str) -> str:
    """Vehicle -> ingest, request/reply (ingest declares the queryable on ``upload('*')``)."""
    return f"{ROOT}/upload/{vehicle_id}"


def obs(tile: str) -> str:
    """Ingest -> matcher: validated observations routed to their target tile."""
    return f"{ROOT}/obs/{tile}"


def assoc(tile: str) -> str:
    """Matcher -> solver: observations with their landmark, and landmark lifecycle events."""
    return f"{ROOT}/assoc/{tile}"


def update(tile: str) -> str:
    """Solver -> publisher: landmark estimates (tile of the landmark's current estimate)."""
    return f"{ROOT}/update/{tile}"


def map_delta(tile: str) -> str:
    """Publisher -> vehicles: map deltas of one tile."""
    return f"{ROOT}/map/{tile}/delta"


def map_snapshot(tile: str) -> str:
    """Publisher queryable: the full map of one tile with its version."""
    return f"{ROOT}/map/{tile}"


def map_snapshot_for(client: str, tile: str) -> str:
    """Publisher queryable: the snapshot of one tile, asked for by ``client`` (an id, the
    vehicle's in secured mode), who the query counts against; the reply has this key."""
    return f"{ROOT}/map/{tile}/by/{client}"


def snapshot_request(key: str) -> tuple[str, str]:
    """``(tile, client)`` of a snapshot query's key: :func:`map_snapshot` keys give
    :data:`ANONYMOUS`, :func:`map_snapshot_for` keys their client; any other key
    ``('', ANONYMOUS)``: a wildcard query (``hdmap/v1/**``, ``.../by/*``) reaches the
    queryables with other chunks, and is limited like an anonymous one. The tile chunk is
    not checked here (the publisher does).

    >>> snapshot_request("hdmap/v1/map/0123"), snapshot_request("hdmap/v1/map/0123/by/veh-1")
    (('0123', 'anonymous'), ('0123', 'veh-1'))
    >>> snapshot_request("hdmap/v1/map/0123/by/*"), snapshot_request("hdmap/v1/**")
    (('', 'anonymous'), ('', 'anonymous'))
    """
    parts = key.split("/")
    if len(parts) < 4 or not key.startswith(f"{ROOT}/map/"):
        return "", ANONYMOUS
    if len(parts) == 4:
        return parts[3], ANONYMOUS
    client = parts[5] if len(parts) == 6 and parts[4] == "by" else ""
    if valid_id(client):
        return parts[3], client
    return "", ANONYMOUS


def snapshot_tile(key: str) -> str:
    """The tile of a :func:`map_snapshot` or :func:`map_snapshot_for` key, '' for any other
    key (a wildcard query such as ``hdmap/v1/**`` reaches the queryable with other chunks).

    >>> snapshot_tile("hdmap/v1/map/0123"), snapshot_tile("hdmap/v1/**")
    ('0123', '')
    >>> snapshot_tile("hdmap/v1/map/0123/by/veh-1"), snapshot_tile("hdmap/v1/map/0123/delta")
    ('0123', '')
    """
    return snapshot_request(key)[0]


def log(stage: str, producer: str, tile: str) -> str:
    """Replay queryable of a producer's durable output log (catch-up after downtime)."""
    return f"{ROOT}/log/{stage}/{producer}/{tile}"


def mark(stage: str, producer: str, consumer: str) -> str:
    """How far a consumer has applied a producer's log (:class:`schemas.LogMark`)."""
    return f"{ROOT}/mark/{stage}/{producer}/{consumer}"


def alive(service: str, region_label: str, instance: str) -> str:
    """Liveliness token of a running service instance."""
    return f"{ROOT}/alive/{service}/{region_label}/{instance}"


def stats(service: str, region_label: str, instance: str) -> str:
    """Stats queryable of a running service instance."""
    return f"{ROOT}/stats/{service}/{region_label}/{instance}"


def handover(service: str, region_label: str) -> str:
    """Handover queryable of a region's matcher or solver (:mod:`schemas.handover`)."""
    return f"{ROOT}/handover/{service}/{region_label}"


def last_chunk(key: str) -> str:
    return key.rsplit("/", 1)[-1]


def chunk(key: str, index: int) -> str:
    """The chunk at ``index`` of a key ('hdmap/v1/obs/12' -> index 3 is '12')."""
    return key.split("/")[index]
