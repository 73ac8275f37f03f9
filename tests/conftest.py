"""Shared fixtures: real routers and service processes on 127.0.0.1, always stopped."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from hdmap.ops.stack import Stack
from hdmap.runtime.bus import open_session


@pytest.fixture
def stack(tmp_path) -> Iterator[Stack]:
    """A Stack whose processes are stopped when the test ends, also on failure."""
    st = Stack(tmp_path / "stack")
    try:
        yield st
    finally:
        st.stop_all()


@pytest.fixture
def router_session(stack):
    """A router process and a client session connected to it."""
    stack.start_router()
    with open_session(stack.bus) as s:
        yield s
