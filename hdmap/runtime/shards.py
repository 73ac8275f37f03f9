"""Instances of one service that split its keys by a stable hash (ingest: vehicles by
id; see docs/operations.md, "Regions")."""

from __future__ import annotations

import zlib


def shard_label(shard: tuple[int, int]) -> str:
    """The suffix a shard adds to an instance's label ('' for the only one).

    >>> shard_label((0, 1)), shard_label((1, 3))
    ('', '-s1of3')
    """
    i, n = shard
    return "" if n == 1 else f"-s{i}of{n}"


def shard_of(key: str, n: int) -> int:
    """The shard (of ``n``) that serves ``key``: a stable hash (CRC-32), the same in
    every process and on every host.

    >>> shard_of("veh-0001", 1), shard_of("veh-0001", 2), shard_of("veh-0004", 2)
    (0, 0, 1)
    """
    return zlib.crc32(key.encode()) % n if n > 1 else 0
