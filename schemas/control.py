"""Service plumbing: the answer of any queryable to a request it cannot serve
(:class:`ErrorReply`) and the counters of one service instance (:class:`Stats`).

>>> ErrorReply.from_bytes(ErrorReply("bad_request", "tile", "not a quadkey").to_bytes()).code
'bad_request'
>>> ErrorReply.from_bytes(ErrorReply("rate", "snapshot.client", "slow down", 0.5).to_bytes())
ErrorReply(code='rate', field='snapshot.client', reason='slow down', retry_after_s=0.5)
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

from schemas.codec import DecodeError, get_float, get_list, get_map, get_str
from schemas.messages import FLOAT_EPOCH_MAX, MAX_RETRY_AFTER_S, Message

_REASON_RE = re.compile(r".{1,200}", re.S)


@dataclass(frozen=True, eq=False)
class ErrorReply(Message):
    """Any queryable's answer to a request it cannot serve.

    ``retry_after_s`` > 0: the refusal is transient (``rate``, ``busy``), the same request
    may be served after that many seconds; 0: no advice (resending soon fails the same way
    or the error says nothing about time). On the wire it is optional and sent only when
    > 0, so an error without it reads as 0 and an older reader ignores it.
    """

    TYPE: ClassVar[str] = "error"
    code: str
    field: str
    reason: str
    retry_after_s: float = 0.0

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {"code": self.code, "field": self.field, "reason": self.reason}
        if self.retry_after_s:  # absent means 0: older encodings and readers stay as they were
            out["retry_after_s"] = float(self.retry_after_s)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> ErrorReply:
        m = cls._open(data)
        retry = 0.0
        if "retry_after_s" in m:  # absent in the errors of older services
            retry = get_float(m, "retry_after_s", 0.0, MAX_RETRY_AFTER_S)
        return cls(
            get_str(m, "code"),
            get_str(m, "field", _REASON_RE),
            get_str(m, "reason", _REASON_RE),
            retry,
        )

    @classmethod
    def of(cls, exc: DecodeError, code: str = "bad_request") -> ErrorReply:
        where = exc.field if exc.index is None else f"{exc.field}[{exc.index}]"
        return cls(code, where[:200] or "message", exc.reason[:200] or "invalid")


@dataclass(frozen=True, eq=False)
class Stats(Message):
    """Reply of ``hdmap/v1/stats/<service>/<region>/<id>``: counters of one instance."""

    TYPE: ClassVar[str] = "stats"
    service: str
    instance: str
    region: list[str]
    started_at: float
    counters: dict[str, float]
    rejected: dict[str, int] = field(default_factory=dict)

    def _encode(self) -> dict[str, Any]:
        return {
            "service": self.service,
            "instance": self.instance,
            "region": list(self.region),
            "started_at": float(self.started_at),
            "counters": dict(self.counters),
            "rejected": dict(self.rejected),
        }

    @classmethod
    def from_bytes(cls, data: bytes) -> Stats:
        m = cls._open(data)
        region = get_list(m, "region", 1000)
        counters = get_map(m, "counters")
        rejected = get_map(m, "rejected")
        for k, v in counters.items():
            if (
                not isinstance(k, str)
                or not isinstance(v, int | float)
                or isinstance(v, bool)
                or not math.isfinite(v)
            ):
                raise DecodeError("counters", f"expected name -> finite number, got {k!r}")
        for k, v in rejected.items():
            if not isinstance(k, str) or not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise DecodeError("rejected", f"expected reason -> count, got {k!r}")
        if not all(isinstance(r, str) for r in region):
            raise DecodeError("region", "expected quadkey prefixes")
        return cls(
            service=get_str(m, "service"),
            instance=get_str(m, "instance"),
            region=region,
            started_at=get_float(m, "started_at", 0.0, FLOAT_EPOCH_MAX),
            counters=counters,
            rejected=rejected,
        )
