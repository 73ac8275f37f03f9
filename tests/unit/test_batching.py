"""How the worker cuts its inbox into batches (:class:`hdmap.runtime.service.Batching`).

The inbox is a queue that records how each item was taken (waiting with the linger left, or
not at all); the service runs the worker loop itself (no bus) on items put in beforehand
and stops once it has seen every one, so each loop is bounded: the only real wait is one
linger (0.2 s) after the last item. Nothing here asserts on time.
"""

from __future__ import annotations

import queue
import threading
from pathlib import Path

import pytest

from hdmap.cli.service import add_arguments, build
from hdmap.runtime.config import ConfigError, from_mapping
from hdmap.runtime.service import Batching, Item, Service, ServiceOptions
from hdmap.runtime.stage import StageService


class Recorded(queue.Queue):
    """A queue that notes, per successful take, whether it could wait (``get`` with a
    timeout) or not (``get_nowait``)."""

    def __init__(self) -> None:
        super().__init__()
        self.takes: list[str] = []

    def get(self, block: bool = True, timeout: float | None = None) -> Item:
        item = super().get(block, timeout)
        self.takes.append("wait" if block and timeout else "nowait")
        return item


class Batches(Service):
    name = "batches"

    def __init__(self, opts: ServiceOptions, expect: int):
        super().__init__(opts)
        self.inbox = Recorded()
        self.expect = expect
        self.batches: list[list[str]] = []
        self.stop = threading.Event()

    def handle(self, items: list[Item]) -> None:
        self.batches.append([it.key for it in items])
        if sum(map(len, self.batches)) >= self.expect:
            self.stop.set()

    def run(self, *keys: str) -> list[list[str]]:
        for k in keys:
            self.inbox.put(Item("entry", k, b""))
        self._loop(self.stop)  # stops in handle once every item was seen
        self.db.close()
        return self.batches


def make(tmp_path: Path, n: int, **batching: object) -> Batches:
    return Batches(ServiceOptions(data_dir=tmp_path, batching=Batching(**batching)), n)


def test_without_linger_a_batch_is_what_is_there(tmp_path: Path):
    svc = make(tmp_path, 3, linger_s=0.0)
    assert svc.run("a", "b", "c") == [["a", "b", "c"]]
    assert svc.inbox.takes == ["wait", "nowait", "nowait"]


def test_a_batch_holds_at_most_max_items(tmp_path: Path):
    assert make(tmp_path, 5, max_items=2, linger_s=0.0).run(*"abcde") == [
        ["a", "b"],
        ["c", "d"],
        ["e"],
    ]


def test_a_lingering_batch_waits_for_items_after_its_first(tmp_path: Path):
    svc = make(tmp_path, 3, linger_s=0.2)
    assert svc.run("a", "b", "c") == [["a", "b", "c"]]
    assert svc.inbox.takes == ["wait", "wait", "wait"]  # each with the linger left


def test_the_default_linger_is_the_service_s():
    opts = ServiceOptions()
    assert Batching().linger_s is None
    assert Service.batch_linger_s == 0.0 and StageService.batch_linger_s > 0.0
    assert Batching(linger_s=0.0).linger_s == 0.0 and opts.batching.max_items == 256


@pytest.mark.parametrize(
    ("table", "field"),
    [
        ({"linger_s": 2.0}, "batching.linger_s"),
        ({"linger_s": -0.1}, "batching.linger_s"),
        ({"max_items": 0}, "batching.max_items"),
        ({"lingers": 0.1}, "matcher.batching.lingers"),
        ({"linger_s": "soon"}, "matcher.batching.linger_s"),
    ],
)
def test_bad_batching_is_refused_naming_the_field(table: dict, field: str):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        from_mapping(Batching, table, "matcher.batching")


def test_a_services_config_sets_a_service_s_batching(tmp_path: Path):
    import argparse

    cfg = tmp_path / "services.toml"
    cfg.write_text(
        "[solver.batching]\nlinger_s = 0.02\nmax_items = 64\n[solver]\nsweep_every_s = 30.0\n"
    )
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["solver", "--config", str(cfg), "--data-dir", str(tmp_path)])
    svc = build(args)
    try:
        assert svc.opts.batching == Batching(max_items=64, linger_s=0.02)
        assert svc.linger_s == 0.02 and svc.config.sweep_every_s == 30.0
    finally:
        svc.db.close()
