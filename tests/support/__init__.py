"""Shared builders of the tests (bounded waits, scenes, service harnesses).

Every test module imports its builders from here, never from another test module."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(pred: Callable[[], bool], timeout: float = 20.0, step: float = 0.05) -> bool:
    """Poll ``pred`` until true or ``timeout`` (bounded loop); its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


class Clock:
    """A settable clock for code that takes one (``clock=``): ``t`` is what it reads."""

    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def start_configured(stack, tmp_path, service: str, table: str, values: dict) -> None:
    """A router and ``service`` alone on ``stack``, started with a config file whose
    ``[table]`` holds ``values`` (e.g. ``ingest.rate_limit``); waits until it is ready."""
    cfg = tmp_path / f"{service}.toml"
    cfg.write_text(f"[{table}]\n" + "".join(f"{k} = {v}\n" for k, v in values.items()))
    stack.start_router()
    stack.start_service(service, (), "--config", str(cfg))
    stack.wait_ready([f"{service}-all"], 60)
