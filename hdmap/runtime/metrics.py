"""Prometheus metrics of a service: the text exposition format 0.0.4, no I/O here.

A service started with a metrics port (``--metrics-port``, ``[NAME.metrics] port``;
:class:`MetricsConfig`) serves ``GET /metrics`` (:mod:`hdmap.runtime.metrics_server`) with:

- every numeric counter of its stats (what ``hdmap status`` shows) as
  ``hdmap_<service>_<counter>``: a **counter** named ``..._total`` when the service counts it
  in its transactions (:meth:`hdmap.runtime.service.Service.count`: durable, it only
  grows, also across restarts), a **gauge** otherwise (backlog, lag, RSS, uptime, the
  per-process counts of the stage loop, ...). A stats name ``base.key`` (``weight.<vehicle>``,
  ``last_txn_error.<cause>``) is ``hdmap_<service>_<base>`` with the label ``key``;
- the refused input by reason as ``hdmap_<service>_rejected_total{reason="..."}`` (its sum is
  the stats' ``rejected``, which is not exported again);
- histograms: the time the worker took per batch (``..._batch_seconds``), the items per
  batch (``..._batch_items``) and the time each item waited in the inbox before its batch
  began (``..._inbox_wait_seconds``; for a stage service this includes the linger).

Every sample has the labels ``service``, ``instance`` and ``region`` (the region label,
``all`` or ``120+121``, with the shard). Names are sanitised to ``[a-zA-Z_:][a-zA-Z0-9_:]*``
(any other character becomes ``_``).

>>> h = Histogram("hdmap_x_batch_seconds", "time per batch", (0.1, 1.0))
>>> h.observe(0.05); h.observe(0.5); h.observe(3.0)
>>> print(render([h.family({"service": "x"})]), end="")
# HELP hdmap_x_batch_seconds time per batch
# TYPE hdmap_x_batch_seconds histogram
hdmap_x_batch_seconds_bucket{service="x",le="0.1"} 1
hdmap_x_batch_seconds_bucket{service="x",le="1.0"} 2
hdmap_x_batch_seconds_bucket{service="x",le="+Inf"} 3
hdmap_x_batch_seconds_sum{service="x"} 3.55
hdmap_x_batch_seconds_count{service="x"} 3
"""

from __future__ import annotations

import itertools
import math
import re
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from hdmap.runtime.config import ConfigError

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
"""The Content-Type of the text exposition format 0.0.4."""

SECONDS_BUCKETS = (
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
)  # fmt: skip
"""Upper bounds (s) of the latency histograms: 1 ms to 30 s."""
ITEMS_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)
"""Upper bounds of the items-per-batch histogram (``[NAME.batching] max_items`` is 256)."""

_INVALID = re.compile(r"[^a-zA-Z0-9_:]")

HELP = {
    "uptime_s": "seconds since this process started",
    "backlog": "items waiting in the inbox",
    "lag_entries": "entries the upstream wrote that this consumer has not applied yet",
    "applying": "1 while the worker handles a batch or a transaction is open",
    "storage_errors": "transactions that failed on the storage",
    "txn_failures": "transactions rolled back in this process",
    "cpu_s": "CPU seconds of this process (user + system)",
    "rss_bytes": "resident memory of this process",
    "entries_applied": "input log entries consumed (dead-lettered ones included)",
    "entries_failed": "input log entries set aside as poison",
    "log_entries": "entries appended to this stage's output log",
    "accepted": "observations recorded and acknowledged to vehicles",
}
"""HELP texts of well-known counters (docs/operations.md, "Watching it"); the others get
a generic one."""


@dataclass(frozen=True)
class MetricsConfig:
    """``[NAME.metrics]`` of a services config file, ``--metrics-port`` / ``--metrics-host``
    of ``hdmap service``: where the service serves ``GET /metrics`` (0: nowhere, the
    default)."""

    port: int = 0
    """TCP port of the metrics endpoint; 0: off."""
    host: str = "127.0.0.1"
    """Address it binds (loopback by default: the endpoint has no authentication)."""

    def __post_init__(self) -> None:
        if isinstance(self.port, bool) or not isinstance(self.port, int):
            raise ConfigError("metrics.port: an integer (0: off)")
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"metrics.port: 0 (off) or a TCP port 1-65535, got {self.port}")
        if not isinstance(self.host, str) or not self.host.strip():
            raise ConfigError("metrics.host: an address to bind, e.g. 127.0.0.1")

    @property
    def enabled(self) -> bool:
        return self.port > 0


def metric_name(*parts: str) -> str:
    """A metric name from parts joined by ``_``, sanitised.

    >>> metric_name("hdmap", "ingest", "rejected[obs.lat]"), metric_name("9lives")
    ('hdmap_ingest_rejected_obs_lat_', '_9lives')
    """
    name = _INVALID.sub("_", "_".join(p for p in parts if p))
    return f"_{name}" if not name or name[0].isdigit() else name


def label_value(v: object) -> str:
    r"""A label value escaped for the text format (backslash, double quote, newline).

    >>> label_value('a"b\\c\nd')
    'a\\"b\\\\c\\nd'
    """
    return str(v).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def help_text(v: str) -> str:
    """A HELP text escaped for the text format (backslash, newline)."""
    return v.replace("\\", "\\\\").replace("\n", "\\n")


def format_value(v: float) -> str:
    """A sample value: integers as such, floats round-trip, ``NaN``, ``+Inf``, ``-Inf``.

    >>> [format_value(v) for v in (3, 2.5, float("inf"), float("nan"), True)]
    ['3', '2.5', '+Inf', 'NaN', '1']
    """
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, int):
        return str(v)
    f = float(v)
    if math.isnan(f):
        return "NaN"
    if math.isinf(f):
        return "+Inf" if f > 0 else "-Inf"
    return repr(f)


def _labels(labels: Mapping[str, object]) -> str:
    if not labels:
        return ""
    inner = ",".join(f'{metric_name(k)}="{label_value(v)}"' for k, v in labels.items())
    return "{" + inner + "}"


@dataclass
class Family:
    """One metric family: its name, type, help and samples (suffix, labels, value)."""

    name: str
    type: str
    help: str
    samples: list[tuple[str, dict[str, object], float]] = field(default_factory=list)


def render(families: Iterable[Family]) -> str:
    """The families in the text exposition format 0.0.4 (``# HELP``, ``# TYPE``, samples),
    ending in a newline."""
    lines: list[str] = []
    for f in families:
        lines.append(f"# HELP {f.name} {help_text(f.help)}")
        lines.append(f"# TYPE {f.name} {f.type}")
        for suffix, labels, value in f.samples:
            lines.append(f"{f.name}{suffix}{_labels(labels)} {format_value(value)}")
    return "\n".join(lines) + "\n" if lines else ""


class Histogram:
    """Observations counted into fixed buckets (thread-safe): ``_bucket`` samples are
    cumulative, the last one ``le="+Inf"`` equals ``_count``."""

    def __init__(self, name: str, help: str, buckets: Sequence[float] = SECONDS_BUCKETS):
        bounds = [float(b) for b in buckets]
        if not bounds or any(not math.isfinite(b) for b in bounds):
            raise ValueError(f"{name}: buckets must be finite numbers")
        if any(a >= b for a, b in itertools.pairwise(bounds)):
            raise ValueError(f"{name}: buckets must increase")
        self.name = name
        self.help = help
        self.bounds = tuple(bounds)
        self._bounds = np.array(bounds)
        self._counts = np.zeros(len(bounds) + 1, np.int64)
        """Per bucket (not cumulative); the last one is above every bound."""
        self._sum = 0.0
        self._lock = threading.Lock()

    def observe(self, value: float) -> None:
        self.observe_many((value,))

    def observe_many(self, values: Iterable[float] | np.ndarray) -> None:
        """Count each value (NaN is ignored) in the first bucket whose bound is >= it (an
        array is counted without a Python step per value)."""
        v = np.asarray(values if isinstance(values, np.ndarray) else list(values), float)
        v = v[~np.isnan(v)]
        if not v.size:
            return
        counts = np.bincount(np.searchsorted(self._bounds, v), minlength=self._counts.size)
        with self._lock:
            self._counts += counts
            self._sum += float(v.sum())

    def snapshot(self) -> tuple[list[int], float, int]:
        """(cumulative counts per bound and +Inf, sum, count), consistent with each other."""
        with self._lock:
            counts, total = self._counts.tolist(), self._sum
        cumulative, running = [], 0
        for c in counts:
            running += c
            cumulative.append(running)
        return cumulative, total, running

    def family(self, labels: Mapping[str, object]) -> Family:
        cumulative, total, count = self.snapshot()
        base = dict(labels)
        les = [format_value(b) for b in self.bounds] + ["+Inf"]
        samples: list[tuple[str, dict[str, object], float]] = [
            ("_bucket", {**base, "le": le}, n) for le, n in zip(les, cumulative, strict=True)
        ]
        samples += [("_sum", base, total), ("_count", base, count)]
        return Family(self.name, "histogram", self.help, samples)


def stats_families(
    service: str,
    labels: Mapping[str, object],
    counters: Mapping[str, float],
    rejected: Mapping[str, float],
    durable: Iterable[str] = (),
) -> list[Family]:
    """The families of a service's stats counters (see the module doc for the rules):
    ``durable`` names the counters the service counts in its transactions (counters), the
    others are gauges; ``rejected`` by reason. Non-numeric values are left out.

    >>> fams = stats_families("ingest", {"service": "ingest"},
    ...     {"accepted": 5, "backlog": 0, "rejected": 2, "last_txn_error.SQLITE_FULL": 1e9},
    ...     {"obs.lat": 2}, durable={"accepted", "rejected"})
    >>> [(f.name, f.type) for f in fams]  # doctest: +NORMALIZE_WHITESPACE
    [('hdmap_ingest_accepted_total', 'counter'), ('hdmap_ingest_backlog', 'gauge'),
     ('hdmap_ingest_last_txn_error', 'gauge'), ('hdmap_ingest_rejected_total', 'counter')]
    >>> fams[2].samples
    [('', {'service': 'ingest', 'key': 'SQLITE_FULL'}, 1000000000.0)]
    >>> fams[3].samples
    [('', {'service': 'ingest', 'reason': 'obs.lat'}, 2)]
    """
    durable = set(durable)
    prefix = metric_name("hdmap", service)
    base = dict(labels)
    fams: dict[str, Family] = {}

    def add(name: str, kind: str, help: str, extra: dict[str, object], value: float) -> None:
        fam = fams.get(name)
        if fam is None:
            fam = fams[name] = Family(name, kind, help)
        elif fam.type != kind:  # two stats names sanitised alike: the first one's type wins
            return
        lab = {**base, **extra}
        if all(s[1] != lab for s in fam.samples):
            fam.samples.append(("", lab, value))

    plain = {k for k in counters if "." not in k}
    for k in sorted(counters):
        v = counters[k]
        if k == "rejected" or isinstance(v, bool) or not isinstance(v, int | float):
            continue
        stem, dot, key = k.partition(".")
        if dot:  # base.key: one family, the key as a label
            name = metric_name(prefix, stem) + ("_by_key" if stem in plain else "")
            add(name, "gauge", f'{service} stats "{stem}.<key>"', {"key": key}, v)
        elif k in durable:
            name = metric_name(prefix, k)
            name = name if name.endswith("_total") else f"{name}_total"
            add(name, "counter", HELP.get(k, f'{service} stats counter "{k}"'), {}, v)
        else:
            add(metric_name(prefix, k), "gauge", HELP.get(k, f'{service} stats "{k}"'), {}, v)
    for reason in sorted(rejected):
        v = rejected[reason]
        if isinstance(v, int | float) and not isinstance(v, bool):
            add(
                metric_name(prefix, "rejected_total"),
                "counter",
                "refused input by reason",
                {"reason": reason},
                v,
            )
    return [fams[n] for n in sorted(fams)]
