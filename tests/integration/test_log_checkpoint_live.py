"""A new publisher after the solver deleted its log (issue 20 point 1): router, ingest,
matcher, solver and publisher as processes, the producers keeping their logs 1 s past
their consumers' marks. Once the solver has deleted update entries, a publisher for a
new region (``1``: the Helsinki town) starts: its catch-up is below what the solver
deleted, and it gets the solver's checkpoints of its tiles and the tail instead of a
refusal. Its map is the first publisher's, landmark for landmark (both answer the
snapshot queries of the town's tiles)."""

from __future__ import annotations

import pytest

from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from schemas import MapSnapshot, keys
from tests.integration.test_region_split import Uploader, payloads
from tests.support import wait_until

pytestmark = pytest.mark.integration


def snapshots(s, tiles: list[str]) -> dict[str, dict[str, dict[int, tuple]]]:
    """Per tile, per answering publisher (by its key), its landmarks."""
    out: dict[str, dict[str, dict[int, tuple]]] = {}
    for t in tiles:
        for key, ok, _e in query(s, keys.map_snapshot(t), timeout=5.0):
            if ok is None:
                continue
            lm = MapSnapshot.from_bytes(ok).landmarks
            rows = {
                int(i): (float(lm.lat[k]), float(lm.lon[k]), int(lm.revision[k]))
                for k, i in enumerate(lm.id.tolist())
            }
            out.setdefault(t, {})[f"{key}#{len(out.get(t, {}))}"] = rows
    return out


def test_a_publisher_started_after_the_solver_deleted_its_log_gets_the_whole_map(
    stack, tmp_path
) -> None:
    cfg = tmp_path / "retention.toml"
    cfg.write_text(
        "".join(
            f"[{n}.retention]\nretain_s = 1.0\nevery_s = 1.0\n"
            for n in ("ingest", "matcher", "solver")
        )
    )
    for n in ("ingest", "matcher", "solver"):
        stack.extra_service_args[n] = ["--config", str(cfg)]
    uploads, tiles = payloads(160)
    town_a = [t for t in tiles if t.startswith("1")]
    stack.start_all()
    with open_session(stack.bus) as s:
        up = Uploader(s, uploads, 0.0)
        up.start()
        up.join(300)
        assert not up.is_alive()
        assert wait_quiet(s, 120.0)
        solver = lambda: totals(collect(s, 2.0))["solver"]  # noqa: E731
        assert wait_until(lambda: solver().get("log_truncated", 0) > 0, 60.0)
        stack.start_service("publisher", ("1",))
        stack.wait_ready(["publisher-1"], 60.0)
        pubs = lambda: [x for x in collect(s, 2.0) if x.service == "publisher"]  # noqa: E731
        assert wait_until(lambda: len(pubs()) == 2, 30.0)

        def caught_up() -> bool:
            c = next(x for x in pubs() if x.region == ["1"]).counters
            return (
                c.get("checkpoints_taken", 0) > 0
                and not c.get("lag_entries", 1)
                and (
                    not c.get("dirty", 1)  # the changes published: the snapshots have them
                )
            )

        assert wait_until(caught_up, 60.0)
        new = next(x for x in pubs() if x.region == ["1"])
        assert new.counters.get("replay_refused", 0) == 0

        def maps() -> list[list[dict]]:
            return [list(by.values()) for by in snapshots(s, town_a).values()]

        def agree() -> bool:
            ms = maps()  # every tile with landmarks answered by both, the same
            return bool(ms) and all(len(m) == 2 and m[0] == m[1] for m in ms)

        # the new publisher publishes what it applied at its next flush (interval_s); polled
        # once a second: the anonymous snapshot budget refuses faster polling
        if not wait_until(agree, 60.0, 1.0):
            diff = {
                t: [sorted(set(a.items()) ^ set(b.items())) if len(m) == 2 else len(m)]
                for t, by in snapshots(s, town_a).items()
                for m in [list(by.values())]
                for a, b in [m if len(m) == 2 else ({}, {})]
            }
            raise AssertionError(
                f"the publishers' maps differ: {diff}; {[x.counters for x in pubs()]}"
            )
        n = sum(len(m[0]) for m in maps())
        assert n >= 20
        print(f"{n} landmarks; checkpoints taken {new.counters['checkpoints_taken']}")
