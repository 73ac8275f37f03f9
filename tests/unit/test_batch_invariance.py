"""The matcher's and the solver's state do not depend on how their input was batched, to
the bit: the gating sums, the assoc log, and every landmark's last published estimate,
covariance and status (a live service gets what its inbox holds; a replay gets any batch
size). The landmark digest of ``tests/unit/test_gating_tick.py`` rounds positions to 1 mm;
this compares the bytes.

The traffic of ``test_gating_tick``: forty passes of eight vehicles at two signs, 0.3 s
apart, every fourth pass uploading twice (ticks of three to six units), so links of many
passes meet in one accumulate call when a batch holds several entries.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hdmap.runtime.service import ServiceOptions
from schemas import LandmarkUpdates, LogEntry
from services.matcher.replay import Sink, read_log, replay
from services.solver.service import SolverService
from tests.unit.test_gating_tick import matcher, traffic


def published(sent: list[tuple[str, bytes]]) -> dict[int, tuple]:
    """Every landmark's last published state (bytes of its estimate, covariance, status,
    counts), removed ones dropped."""
    last: dict[int, tuple] = {}
    for _key, payload in sent:
        u = LandmarkUpdates.from_bytes(LogEntry.from_bytes(payload).body)
        lm = u.landmarks
        for k, i in enumerate(lm.id.tolist()):
            last[i] = (
                lm.lat[k].tobytes(),
                lm.lon[k].tobytes(),
                lm.h[k].tobytes(),
                lm.cov[k].tobytes(),
                int(lm.status[k]),
                int(lm.n_obs[k]),
                int(lm.n_passes[k]),
            )
        for i in u.removed.id.tolist():
            last.pop(i, None)
    return last


def test_matcher_and_solver_state_are_the_same_however_batched(tmp_path: Path) -> None:
    entries = traffic(tmp_path / "gen")
    sums, logs = set(), []
    for batch in (1, 7, len(entries)):
        m = matcher(tmp_path / f"m{batch}")
        replay(m, entries, batch)
        rows = np.array(sorted(lm.row for lm in m.state.landmarks.values()), np.int64)
        sums.add(b"".join(m.sums.pack_rows(rows)))
        logs.append(read_log(m.db_path, "assoc"))
        m.db.close()
    assert len(sums) == 1
    bodies = {tuple(e.body for e in log) for log in logs}
    assert len(bodies) == 1  # the same assoc log, entry by entry
    assoc = logs[0]
    states, sums = [], set()
    for batch in (1, 3, len(assoc)):
        s = SolverService(ServiceOptions(data_dir=tmp_path / f"s{batch}"))
        sink = Sink(keep=True)
        s.pubs = sink  # type: ignore[assignment]
        replay(s, assoc, batch)  # type: ignore[arg-type]
        rows = np.array(sorted(lm.row for lm in s.state.landmarks.values()), np.int64)
        sums.add(b"".join(s.sums.pack_rows(rows)))
        states.append(published(sink.sent))
        s.db.close()
    assert len(states[0]) == 2 and all(st == states[0] for st in states[1:])
    assert len(sums) == 1
