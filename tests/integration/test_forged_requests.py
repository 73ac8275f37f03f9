"""Forged or odd requests from a client: liveliness tokens that name no one service instance
(a wildcard, a token with no service behind it) do not change what the status client
counts; snapshot queries that name no one tile get an error naming the field."""

from __future__ import annotations

import pytest

from hdmap.ops.status import collect
from hdmap.runtime.bus import query
from schemas import ErrorReply, keys
from tests.support import wait_until

pytestmark = pytest.mark.integration


def test_wildcard_and_orphan_tokens_do_not_count_a_service(stack, router_session):
    stack.start_service("ingest")
    assert wait_until(lambda: len(collect(router_session, 1.0)) == 1, timeout=30)
    forged = [
        router_session.liveliness().declare_token(f"{keys.ROOT}/alive/ingest/*/*"),
        router_session.liveliness().declare_token(f"{keys.ROOT}/alive/ingest/**"),
        router_session.liveliness().declare_token(f"{keys.ROOT}/alive/ingest/all/nobody"),
    ]
    try:
        stats = collect(router_session, 1.0)
        assert [s.service for s in stats] == ["ingest"]
    finally:
        for t in forged:
            t.undeclare()


def test_snapshot_queries_that_name_no_tile_get_an_error_naming_the_field(stack, router_session):
    stack.start_service("publisher")
    assert wait_until(lambda: len(collect(router_session, 1.0)) == 1, timeout=30)
    for selector in (f"{keys.ROOT}/**", f"{keys.ROOT}/map/**", f"{keys.ROOT}/map/*"):
        replies = query(router_session, selector, timeout=3.0)
        errors = [ErrorReply.from_bytes(err) for _k, ok, err in replies if err is not None]
        assert errors and all(e.field == "tile" for e in errors), (selector, replies)
    (stats,) = collect(router_session, 1.0)
    assert stats.rejected.get("snapshot.tile", 0) >= 3
    log = (stack.data_dir / "logs").glob("publisher*.log")
    assert not any("Traceback" in p.read_text() for p in log)
