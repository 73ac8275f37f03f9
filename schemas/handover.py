"""Handing a region's state over (``hdmap region split`` / ``merge``): operator tool <->
a matcher or solver instance, on ``hdmap/v1/handover/<service>/<region>``.

The tool asks an instance to ``pause`` (it applies nothing more: its input stays in its
producers' logs; it still serves its own log, so its consumers drain it). Several
regions joined into one are first brought to one position of their input (``cut``: each
applies its entries up to the same ``gseq`` of every producer, then holds; ``at_cut`` in
the reply), so that the joined instance goes on from a state the unsplit region had. The
tool watches the ``status`` until every consumer's mark reached the instance's log head, reads its
checkpoint (its database as of the pause) in ``state`` chunks from ``offset``, and tells it
to ``stop`` (or ``resume``, to call the handover off).

>>> r = HandoverReply("matcher", "m-1", "12", True, 40, (("s-1", 40, 1.5),), 8, 0, b"SQLite f")
>>> HandoverReply.from_bytes(r.to_bytes()).marks
(('s-1', 40, 1.5),)
>>> HandoverRequest.from_bytes(HandoverRequest("state", 4096).to_bytes())
HandoverRequest(op='state', offset=4096)
>>> HandoverRequest.from_bytes(HandoverRequest("cut", cut=(("ingest-0", 90),)).to_bytes()).cut
(('ingest-0', 90),)
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, ClassVar

from schemas.codec import DecodeError, get_bytes, get_float, get_int, get_list, get_str
from schemas.messages import Message

OPS = ("status", "pause", "cut", "resume", "state", "stop")
"""What a handover request asks."""
CHUNK_BYTES = 8 * 1024 * 1024
"""Most checkpoint bytes in one reply."""
MAX_MARKS = 1024
MAX_PRODUCERS = 1024
"""Most producers in a cut or an instance's input positions."""

_OP_RE = re.compile("|".join(OPS))
_SERVICE_RE = re.compile(r"matcher|solver")
_REGION_RE = re.compile(r"all|[0-3]{1,24}(\+[0-3]{1,24}){0,255}")


@dataclass(frozen=True, eq=False)
class HandoverRequest(Message):
    """Tool -> instance: ``op`` (one of :data:`OPS`); ``offset``: the first checkpoint byte
    wanted (``state`` only); ``cut``: ``(producer, gseq)`` pairs, the input position to
    apply up to and hold at (``cut`` only; a producer not named: none of its entries)."""

    TYPE: ClassVar[str] = "handover_request"
    op: str
    offset: int = 0
    cut: tuple[tuple[str, int], ...] = ()

    def _encode(self) -> dict[str, Any]:
        return {
            "op": self.op,
            "offset": int(self.offset),
            "cut": [[p, int(g)] for p, g in self.cut],
        }

    @classmethod
    def from_bytes(cls, data: bytes) -> HandoverRequest:
        m = cls._open(data)
        return cls(
            get_str(m, "op", _OP_RE, " or ".join(OPS)),
            get_int(m, "offset", 0, 2**50),
            _positions(m, "cut") if "cut" in m else (),  # a tool from before cuts
        )

    def __repr__(self) -> str:
        cut = f", cut={self.cut!r}" if self.cut else ""
        return f"HandoverRequest(op={self.op!r}, offset={self.offset}{cut})"


@dataclass(frozen=True, eq=False)
class HandoverReply(Message):
    """Instance -> tool: who answers, whether it is paused, its output log's head (the last
    ``gseq`` it wrote) and its consumers' marks ``(consumer, gseq, age_s)`` (what each has
    applied of it, and how long ago it said so), and once paused the checkpoint's ``size``
    (for ``state``, the chunk ``data`` at ``offset``); ``inputs``: ``(producer, gseq)``,
    the last entry of each producer's log it applied; ``at_cut``: it has applied its
    region's entries up to the cut it was given and holds there (its checkpoint is of
    that state)."""

    TYPE: ClassVar[str] = "handover_reply"
    service: str
    instance: str
    region: str
    paused: bool
    head: int
    marks: tuple[tuple[str, int, float], ...]
    size: int = 0
    offset: int = 0
    data: bytes = b""
    inputs: tuple[tuple[str, int], ...] = ()
    at_cut: bool = False

    def _encode(self) -> dict[str, Any]:
        return {
            "service": self.service,
            "instance": self.instance,
            "region": self.region,
            "paused": int(bool(self.paused)),
            "head": int(self.head),
            "marks": [[c, int(g), float(a)] for c, g, a in self.marks],
            "size": int(self.size),
            "offset": int(self.offset),
            "data": bytes(self.data),
            "inputs": [[p, int(g)] for p, g in self.inputs],
            "at_cut": int(bool(self.at_cut)),
        }

    @classmethod
    def from_bytes(cls, data: bytes) -> HandoverReply:
        m = cls._open(data)
        marks = []
        for i, x in enumerate(get_list(m, "marks", MAX_MARKS)):
            if not (isinstance(x, list) and len(x) == 3):
                raise DecodeError("marks", "expected [consumer, gseq, age_s]", i)
            one = {"consumer": x[0], "gseq": x[1], "age_s": x[2]}
            marks.append(
                (get_str(one, "consumer"), get_int(one, "gseq", 0, 2**63 - 1),
                 get_float(one, "age_s", 0.0, 1e12))
            )  # fmt: skip
        chunk = get_bytes(m, "data")
        if len(chunk) > CHUNK_BYTES:
            raise DecodeError("data", f"more than {CHUNK_BYTES} bytes")
        return cls(
            get_str(m, "service", _SERVICE_RE),
            get_str(m, "instance"),
            get_str(m, "region", _REGION_RE, "'all' or quadkey prefixes joined by '+'"),
            bool(get_int(m, "paused", 0, 1)),
            get_int(m, "head", 0, 2**63 - 1),
            tuple(marks),
            get_int(m, "size", 0, 2**50),
            get_int(m, "offset", 0, 2**50),
            chunk,
            _positions(m, "inputs"),
            bool(get_int(m, "at_cut", 0, 1)),
        )


def _positions(m: dict[str, Any], name: str) -> tuple[tuple[str, int], ...]:
    """``[[producer, gseq], ...]`` as pairs, each producer once."""
    out: dict[str, int] = {}
    for i, x in enumerate(get_list(m, name, MAX_PRODUCERS)):
        if not (isinstance(x, list) and len(x) == 2):
            raise DecodeError(name, "expected [producer, gseq]", i)
        one = {"producer": x[0], "gseq": x[1]}
        try:
            p, g = get_str(one, "producer"), get_int(one, "gseq", 0, 2**63 - 1)
        except DecodeError as exc:
            raise DecodeError(name, f"{exc.field}: {exc.reason}", i) from exc
        if p in out:
            raise DecodeError(name, f"producer {p} named twice", i)
        out[p] = g
    return tuple(sorted(out.items()))
