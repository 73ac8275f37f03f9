"""Processes started by a :class:`hdmap.ops.stack.Stack` end when their starter is gone.

The stack starts the router and the services in sessions of their own (a Ctrl-C in the
terminal reaches the starter, which stops them in order). If the starter itself is killed
(SIGKILL, a crashed test run, a CI timeout), nothing would stop them: they would keep
their ports and data directories. So the stack passes its process id in
:data:`PARENT_ENV`, and such a child watches its parent: once it is re-parented (its
parent died), it sends itself SIGTERM, which every hdmap process handles by closing
cleanly.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time

log = logging.getLogger(__name__)

PARENT_ENV = "HDMAP_PARENT_PID"
"""Set by the stack in its children's environment: the starter's process id."""


def watch_parent(poll_s: float = 1.0) -> threading.Thread | None:
    """If this process was started by a stack, a daemon thread that SIGTERMs it once the
    starter is gone (polled every ``poll_s``); None otherwise. The variable is removed
    from the environment, so processes this one starts do not inherit the watch.

    >>> os.environ.pop(PARENT_ENV, None) and None
    >>> watch_parent() is None
    True
    """
    raw = os.environ.pop(PARENT_ENV, None)
    if raw is None:
        return None
    try:
        starter = int(raw)
    except ValueError:
        log.warning("ignoring %s=%r (not a process id)", PARENT_ENV, raw)
        return None

    def watch() -> None:
        while os.getppid() == starter:
            time.sleep(poll_s)
        log.warning("starter process %d is gone: stopping", starter)
        os.kill(os.getpid(), signal.SIGTERM)

    t = threading.Thread(target=watch, name="parent-watch", daemon=True)
    t.start()
    return t
