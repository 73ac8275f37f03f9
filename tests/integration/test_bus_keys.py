"""Data-path puts to many distinct keys through a real router: every one arrives, and the
writer keeps nothing per key (an upload spread over many tiles costs what its size costs).
The cost per new key is measured in ``benchmarks/bench_keys.py``."""

from __future__ import annotations

import threading

import pytest

from hdmap.runtime.bus import Publishers, open_session
from tests.support import wait_until

pytestmark = pytest.mark.integration


def test_puts_to_many_new_keys_all_arrive_and_nothing_is_kept_per_key(stack, router_session):
    got: set[str] = set()
    lock = threading.Lock()

    def on_sample(s) -> None:
        with lock:
            got.add(str(s.key_expr))

    sub = router_session.declare_subscriber("test/keys/**", on_sample)
    try:
        with open_session(stack.bus) as s:
            pubs = Publishers(s)
            before = dict(vars(pubs))
            keys = [f"test/keys/{i // 100}/{i}" for i in range(5000)]
            for k in keys:
                pubs.put(k, b"x")
            assert vars(pubs) == before  # no registry that grows with the keys
            assert wait_until(lambda: len(got) == len(keys), timeout=30)
            pubs.close()
    finally:
        sub.undeclare()
    assert got == set(keys)
