"""Every Zenoh key expression of the system, in one place (see schemas/README.md).

``<tile>`` is one quadkey chunk; a region is a quadkey prefix selected with the
sub-chunk wildcard ``$*`` (``hdmap/v1/obs/120210$*`` matches every tile under
``120210``).

>>> obs('1202')
'hdmap/v1/obs/1202'
>>> obs(region('120'))
'hdmap/v1/obs/120$*'
>>> obs(region(''))
'hdmap/v1/obs/*'
"""

from __future__ import annotations

ROOT = "hdmap/v1"
ANY = "*"


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


def snapshot_tile(key: str) -> str:
    """The tile of a :func:`map_snapshot` key, '' for any other key (a wildcard query such
    as ``hdmap/v1/**`` reaches the queryable with fewer chunks).

    >>> snapshot_tile("hdmap/v1/map/0123"), snapshot_tile("hdmap/v1/**")
    ('0123', '')
    """
    parts = key.split("/")
    return parts[3] if len(parts) == 4 and key.startswith(f"{ROOT}/map/") else ""


def log(stage: str, producer: str, tile: str) -> str:
    """Replay queryable of a producer's durable output log (catch-up after downtime)."""
    return f"{ROOT}/log/{stage}/{producer}/{tile}"


def alive(service: str, region_label: str, instance: str) -> str:
    """Liveliness token of a running service instance."""
    return f"{ROOT}/alive/{service}/{region_label}/{instance}"


def stats(service: str, region_label: str, instance: str) -> str:
    """Stats queryable of a running service instance."""
    return f"{ROOT}/stats/{service}/{region_label}/{instance}"


def last_chunk(key: str) -> str:
    return key.rsplit("/", 1)[-1]


def chunk(key: str, index: int) -> str:
    """The chunk at ``index`` of a key ('hdmap/v1/obs/12' -> index 3 is '12')."""
    return key.split("/")[index]
