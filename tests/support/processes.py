"""Subprocesses a test starts and must leave nothing of, also on failure."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[2]


@contextlib.contextmanager
def running(argv: list[str], log: Path) -> Iterator[subprocess.Popen]:
    """A subprocess writing to ``log`` (cwd: the repository). Its descendants are watched
    while it runs, so that none outlives a failed test; on leaving, it is sent SIGTERM
    (killed after 30 s) and every descendant seen is killed."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with open(log, "ab") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, cwd=REPO, env=env)
    seen: dict[int, psutil.Process] = {}
    stop = threading.Event()

    def remember() -> None:
        with contextlib.suppress(psutil.Error):
            for c in psutil.Process(proc.pid).children(recursive=True):
                seen.setdefault(c.pid, c)

    def watch() -> None:
        while not stop.wait(0.2):
            remember()

    t = threading.Thread(target=watch, daemon=True)
    t.start()
    try:
        yield proc
    finally:
        stop.set()
        t.join(5)
        remember()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
        for c in seen.values():
            with contextlib.suppress(psutil.Error):
                c.kill()
        psutil.wait_procs(list(seen.values()), timeout=10)
