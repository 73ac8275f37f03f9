"""Identifier layouts shared between processes: landmark ids and pass keys.

Every service that reads or writes these ids uses this module, so the layout is one
contract, not a detail of the process that first made it.

Landmark id (64 bits, unsigned)::

    (home tile quadkey read as a base-4 integer) << COUNTER_BITS | counter

The home tile is the tile the landmark was created in; the counter (1 .. 2^24 - 1) is
the matcher's per-tile sequence. An id names one landmark for good: a merged or retired
landmark's id is never given to another one.

Pass key (63 bits, non-zero): a stable hash of (vehicle, pass id), the same in every
process, used as the estimator's cluster key; rays a pass sent while its vehicle was on
probation form a cluster of their own. A hold key names all of a vehicle's held passes.

>>> hex(landmark_id('0123', 5))
'0x1b000005'
>>> home_tile(landmark_id('0123', 5), zoom=4)
'0123'
"""

from __future__ import annotations

import hashlib

COUNTER_BITS = 24
"""Low bits of a landmark id that hold the per-tile counter."""


def landmark_id(home_tile: str, counter: int) -> int:
    """The id of the ``counter``-th landmark created in ``home_tile`` (a quadkey)."""
    if not 0 < counter < (1 << COUNTER_BITS):
        raise ValueError("landmark counter out of range for its tile")
    return (int(home_tile, 4) << COUNTER_BITS) | counter


def home_tile(landmark_id: int, zoom: int) -> str:
    """The creation tile embedded in a landmark id, as a quadkey of ``zoom`` digits."""
    q = landmark_id >> COUNTER_BITS
    digits = []
    for _ in range(zoom):
        digits.append(str(q & 3))
        q >>= 2
    return "".join(reversed(digits))


def _key63(text: str) -> int:
    h = hashlib.blake2b(text.encode(), digest_size=8).digest()
    return int.from_bytes(h, "little") & ((1 << 63) - 1) or 1


def pass_key(vehicle: str, pass_id: int, held: bool = False) -> int:
    """Stable 63-bit cluster key of (vehicle, pass), the same in every process; the rays a
    pass sent while its vehicle was on probation form a cluster of their own (``held``).

    >>> pass_key("veh-1", 7) == pass_key("veh-1", 7) != pass_key("veh-1", 8)
    True
    >>> pass_key("veh-1", 7, held=True) != pass_key("veh-1", 7)
    True
    """
    return _key63(f"{vehicle}\x00{pass_id}" + ("\x00held" if held else ""))


def hold_key(vehicle: str) -> int:
    """Non-zero key of a vehicle's held passes (``LandmarkSums.accumulate(hold=...)``)."""
    return _key63(f"{vehicle}\x00hold")
