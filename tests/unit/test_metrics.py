"""Prometheus metrics: the text exposition format 0.0.4 (hdmap/runtime/metrics.py), the
endpoint (hdmap/runtime/metrics_server.py) and a service's batches measured in its worker
(hdmap/runtime/service.py); the option on ``hdmap service`` (hdmap/cli/service.py).

The endpoint is served on 127.0.0.1 (an ephemeral port); every wait is bounded."""

from __future__ import annotations

import math
import re
import socket
import threading
import time
import urllib.error
import urllib.request
from collections import Counter

import pytest

from hdmap.cli.service import metrics_config
from hdmap.runtime.config import ConfigError
from hdmap.runtime.metrics import (
    CONTENT_TYPE,
    Histogram,
    MetricsConfig,
    format_value,
    label_value,
    metric_name,
    render,
    stats_families,
)
from hdmap.runtime.metrics_server import MetricsServer
from hdmap.runtime.service import Item, Service, ServiceOptions
from schemas import Stats

NAME = re.compile(r"^[a-zA-Z_:][a-zA-Z0-9_:]*$")
SAMPLE = re.compile(
    r"^(?P<name>[a-zA-Z_:][a-zA-Z0-9_:]*)"
    r'(?P<labels>\{(?:[a-zA-Z_][a-zA-Z0-9_]*="(?:[^"\\\n]|\\.)*",?)*\})? '
    r"(?P<value>\S+)$"
)
LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="((?:[^"\\\n]|\\.)*)"')


def parse(text: str) -> dict[str, dict]:
    """The families of an exposition, checked line by line against the 0.0.4 format: each
    family's ``# HELP`` and ``# TYPE`` once and before its samples, samples of one family
    together, every value a number."""
    assert text.endswith("\n")
    fams: dict[str, dict] = {}
    current = ""
    for line in text.splitlines():
        if line.startswith("# HELP "):
            name = line.split(" ", 3)[2]
            assert NAME.match(name) and name not in fams, line
            fams[name] = {"help": line.split(" ", 3)[3], "type": None, "samples": []}
            current = name
        elif line.startswith("# TYPE "):
            _, _, name, kind = line.split(" ")
            assert name == current and fams[name]["type"] is None, line
            assert kind in ("counter", "gauge", "histogram", "summary", "untyped")
            fams[name]["type"] = kind
        else:
            m = SAMPLE.match(line)
            assert m, f"not a sample line: {line!r}"
            name = m["name"]
            base = re.sub(r"_(bucket|sum|count)$", "", name)
            family = name if fams.get(current, {}).get("type") != "histogram" else base
            assert family == current, f"{line!r} outside its family {current}"
            labels = dict(LABEL.findall(m["labels"] or ""))
            value = float(m["value"]) if m["value"] not in ("+Inf", "-Inf", "NaN") else m["value"]
            fams[current]["samples"].append((name, labels, value))
    assert all(f["type"] for f in fams.values())
    return fams


def check_histogram(fam: dict) -> None:
    """Buckets cumulative and ending in +Inf equal to _count, per label set."""
    by_labels: dict[tuple, list] = {}
    sums, counts = {}, {}
    for name, labels, value in fam["samples"]:
        key = tuple(sorted((k, v) for k, v in labels.items() if k != "le"))
        if name.endswith("_bucket"):
            by_labels.setdefault(key, []).append((labels["le"], value))
        elif name.endswith("_sum"):
            sums[key] = value
        elif name.endswith("_count"):
            counts[key] = value
    assert by_labels and by_labels.keys() == sums.keys() == counts.keys()
    for key, buckets in by_labels.items():
        les = [math.inf if le == "+Inf" else float(le) for le, _ in buckets]
        assert les == sorted(les) and les[-1] == math.inf
        values = [v for _, v in buckets]
        assert values == sorted(values), "buckets are cumulative"
        assert values[-1] == counts[key]


# -- the format ---------------------------------------------------------------------------------


def test_histogram_buckets_are_cumulative_inclusive_and_end_in_inf() -> None:
    h = Histogram("hdmap_x_seconds", "x", (0.1, 1.0, 10.0))
    h.observe_many([0.05, 0.1, 0.5, 1.0, 2.0, 100.0, float("nan")])
    cumulative, total, count = h.snapshot()
    assert cumulative == [2, 4, 5, 6]  # le is inclusive: 0.1 counts in le="0.1"
    assert count == 6 and total == pytest.approx(103.65)
    fams = parse(render([h.family({"service": "x"})]))
    fam = fams["hdmap_x_seconds"]
    assert fam["type"] == "histogram" and fam["help"] == "x"
    check_histogram(fam)
    names = [s[0] for s in fam["samples"]]
    assert names[-2:] == ["hdmap_x_seconds_sum", "hdmap_x_seconds_count"]
    assert fam["samples"][-4][1]["le"] == "10.0" and fam["samples"][-3][1]["le"] == "+Inf"


def test_histogram_refuses_bad_buckets_and_counts_from_threads() -> None:
    for bad in ((), (1.0, 1.0), (2.0, 1.0), (1.0, math.inf)):
        with pytest.raises(ValueError):
            Histogram("h", "h", bad)
    h = Histogram("h", "h", (1.0,))

    def work() -> None:
        for _ in range(1000):
            h.observe(0.5)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert h.snapshot()[2] == 4000


def test_stats_become_counters_gauges_and_rejected_by_reason() -> None:
    counters = {
        "accepted": 12,
        "uploads": 3,
        "backlog": 0,
        "uptime_s": 12.5,
        "rejected": 5,
        "weight.veh-1": 0.25,
        "weight.veh-2": 0.5,
        "last_txn_error.SQLITE_FULL": 1.7e9,
        "odd name-with.dots": 1,
        "ratio": float("nan"),
    }
    rejected = {"obs.lat": 3, 'batch."key"': 2}
    labels = {"service": "ingest", "instance": "ingest-all-1", "region": "all"}
    text = render(
        stats_families("ingest", labels, counters, rejected, {"accepted", "uploads", "rejected"})
    )
    fams = parse(text)
    assert fams["hdmap_ingest_accepted_total"]["type"] == "counter"
    assert fams["hdmap_ingest_uploads_total"]["type"] == "counter"
    assert fams["hdmap_ingest_backlog"]["type"] == "gauge"
    assert fams["hdmap_ingest_uptime_s"]["type"] == "gauge"
    assert "hdmap_ingest_rejected" not in fams  # the sum of the reasons, not again
    rej = fams["hdmap_ingest_rejected_total"]
    assert rej["type"] == "counter"
    assert {s[1]["reason"]: s[2] for s in rej["samples"]} == {
        "obs.lat": 3.0,
        'batch.\\"key\\"': 2.0,  # escaped in the exposition
    }
    weights = fams["hdmap_ingest_weight"]["samples"]
    assert {s[1]["key"]: s[2] for s in weights} == {"veh-1": 0.25, "veh-2": 0.5}
    assert fams["hdmap_ingest_last_txn_error"]["samples"][0][1]["key"] == "SQLITE_FULL"
    assert "hdmap_ingest_odd_name_with" in fams  # sanitised; the rest is the key
    assert fams["hdmap_ingest_ratio"]["samples"][0][2] == "NaN"
    for fam in fams.values():
        for _name, lab, _v in fam["samples"]:
            assert {"service", "instance", "region"} <= lab.keys()
            assert lab["instance"] == "ingest-all-1"
    assert "# HELP hdmap_ingest_backlog items waiting in the inbox" in text


def test_names_labels_and_values_are_sanitised_and_escaped() -> None:
    assert metric_name("hdmap", "matcher", "a.b-c[d]") == "hdmap_matcher_a_b_c_d_"
    assert metric_name("0x") == "_0x"
    assert label_value('a\\b"c\nd') == 'a\\\\b\\"c\\nd'
    assert [format_value(v) for v in (0, 10**20, 0.1, -math.inf, 1e-9)] == [
        "0",
        "100000000000000000000",
        "0.1",
        "-Inf",
        "1e-09",
    ]
    assert render([]) == ""


def test_metrics_config_is_checked_and_the_options_override_the_file() -> None:
    assert MetricsConfig() == MetricsConfig(port=0, host="127.0.0.1")
    assert not MetricsConfig().enabled and MetricsConfig(port=9101).enabled
    for bad in ({"port": -1}, {"port": 70000}, {"port": True}, {"host": " "}):
        with pytest.raises(ConfigError, match="metrics"):
            MetricsConfig(**bad)  # type: ignore[arg-type]
    table = {"metrics": {"port": 9101, "host": "0.0.0.0"}}
    assert metrics_config("solver", table) == MetricsConfig(9101, "0.0.0.0")
    assert metrics_config("solver", table, port=0) == MetricsConfig(0, "0.0.0.0")
    assert metrics_config("solver", {}, port=9200) == MetricsConfig(9200, "127.0.0.1")
    with pytest.raises(ConfigError, match=r"solver\.metrics\.prot: unknown key"):
        metrics_config("solver", {"metrics": {"prot": 1}})


# -- the endpoint -------------------------------------------------------------------------------


def scrape(port: int, path: str = "/metrics") -> tuple[int, str, str]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as r:
            return r.status, r.headers["Content-Type"], r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers["Content-Type"], exc.read().decode()


def test_server_answers_metrics_404_elsewhere_500_on_a_failed_render_and_closes() -> None:
    state = {"fail": False}

    def body() -> str:
        if state["fail"]:
            raise RuntimeError("boom")
        return "# HELP a a\n# TYPE a gauge\na 1\n"

    srv = MetricsServer(MetricsConfig(port=0), body)  # port 0 here: any free one
    port = srv.address[1]
    srv.start()
    try:
        assert scrape(port) == (200, CONTENT_TYPE, "# HELP a a\n# TYPE a gauge\na 1\n")
        assert scrape(port, "/metrics?x=1")[0] == 200
        assert scrape(port, "/")[0] == 404
        state["fail"] = True
        assert scrape(port)[0] == 500
    finally:
        srv.close()
    with pytest.raises(OSError), socket.create_connection(("127.0.0.1", port), timeout=2):
        pass


def test_a_port_in_use_is_a_config_error_naming_it() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(
            ConfigError, match=rf"metrics\.port: cannot serve on 127\.0\.0\.1:{port}"
        ):
            MetricsServer(MetricsConfig(port=port), lambda: "")


class Quiet(Service):
    """A service that counts what it handles (no bus: only its worker's step is used)."""

    name = "quiet"

    def handle(self, items: list[Item]) -> None:
        with self.transaction():
            self.count("handled", len(items))
            if any(it.kind == "bad" for it in items):
                self.reject("item.kind")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_service_measures_its_batches_only_with_a_port(tmp_path) -> None:
    off = Quiet(ServiceOptions(data_dir=tmp_path / "off"))
    try:
        assert off.metrics.server is None and not off.metrics.enabled
        off.step([Item("x", "k", b"")])
        assert off.metrics.batch_seconds.snapshot()[2] == 0  # nothing measured when off
    finally:
        off.db.close()

    svc = Quiet(ServiceOptions(data_dir=tmp_path / "on", metrics=MetricsConfig(free_port())))
    try:
        now = time.monotonic()
        svc.step([Item("x", "k", b"", received=now - 0.5), Item("bad", "k", b"", received=now)])
        svc.step([Item("x", "k", b"")])
        fams = parse(svc.metrics.render())
        for name in ("batch_seconds", "batch_items", "inbox_wait_seconds"):
            fam = fams[f"hdmap_quiet_{name}"]
            assert fam["type"] == "histogram"
            check_histogram(fam)
        count = {s[0]: s[2] for s in fams["hdmap_quiet_batch_items"]["samples"]}
        assert count["hdmap_quiet_batch_items_count"] == 2
        assert count["hdmap_quiet_batch_items_sum"] == 3
        waits = fams["hdmap_quiet_inbox_wait_seconds"]["samples"]
        assert {s[0]: s[2] for s in waits}["hdmap_quiet_inbox_wait_seconds_count"] == 3
        over = [s[2] for s in waits if s[1].get("le") == "0.25"]
        assert over == [2.0]  # the item that waited 0.5 s is above 0.25 s
        assert fams["hdmap_quiet_handled_total"]["type"] == "counter"
        assert fams["hdmap_quiet_handled_total"]["samples"][0][2] == 3
        assert fams["hdmap_quiet_rejected_total"]["samples"][0][1]["reason"] == "item.kind"
        assert fams["hdmap_quiet_backlog"]["type"] == "gauge"
        lab = fams["hdmap_quiet_backlog"]["samples"][0][1]
        assert lab == {"service": "quiet", "instance": svc.instance, "region": "all"}
        # the scrape and the stats agree on the committed counters
        st: Stats = svc.stats()
        assert st.counters["handled"] == 3 and Counter(st.rejected) == Counter({"item.kind": 1})
    finally:
        svc.metrics.close()
        svc.db.close()
