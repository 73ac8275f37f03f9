"""The progress line of long work (hdmap/ops/progress.py): plain lines every N % on a log,
one line redrawn in place on a terminal, the ETA, turning it off, workers reporting from
other processes. Time is a fake clock: nothing waits on real time."""

from __future__ import annotations

import io
from concurrent.futures import ProcessPoolExecutor

import pytest

from hdmap.ops.progress import (
    ENV_OFF,
    Progress,
    Relay,
    format_duration,
    progress_wanted,
    pump,
    relayed,
    wait_relayed,
)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def log_bar(total: float | None, **kw) -> tuple[Progress, io.StringIO, Clock]:
    out, clock = io.StringIO(), Clock()
    bar = Progress(total, "passes", stream=out, tty=False, enabled=True, clock=clock, **kw)
    return bar, out, clock


def test_a_log_gets_a_line_every_10_percent_with_rate_and_eta() -> None:
    bar, out, clock = log_bar(1000)
    for _ in range(1000):
        clock.t += 0.5
        bar.update()
    bar.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 10
    assert lines[0] == "passes: 100/1000 (10 %), 2.00/s, ETA 7m30s"
    assert lines[4] == "passes: 500/1000 (50 %), 2.00/s, ETA 4m10s"
    assert lines[-1] == "passes: 1000/1000 (100 %), 2.00/s, 8m20s"  # done: the time it took
    assert "\r" not in out.getvalue()


def test_one_line_per_update_however_many_marks_it_crosses_and_a_last_line_if_short() -> None:
    bar, out, clock = log_bar(10, every_pct=25)
    clock.t += 1
    bar.update(7)  # 70 %: crosses 25 and 50, one line
    clock.t += 1
    bar.update(1)  # 80 %: crosses 75
    clock.t += 1
    bar.close()  # stopped short of 100 %: a last line says where
    assert out.getvalue().splitlines() == [
        "passes: 7/10 (70 %), 7.00/s, ETA 0s",
        "passes: 8/10 (80 %), 4.00/s, ETA 0s",
        "passes: 8/10 (80 %), 2.67/s, ETA 1s",
    ]


def test_eta_is_the_mean_rate_so_far_and_unknown_before_any_work() -> None:
    bar, _out, clock = log_bar(100)
    assert bar.eta_s() is None
    clock.t += 30.0
    bar.set(25)
    assert bar.eta_s() == pytest.approx(90.0)  # 25 in 30 s: 75 more take 90 s
    clock.t += 10.0
    bar.set(50)
    assert bar.eta_s() == pytest.approx(40.0)
    bar.set(100)
    assert bar.eta_s() == 0.0
    assert log_bar(None)[0].eta_s() is None


def test_a_terminal_gets_one_line_redrawn_in_place_at_most_every_redraw_s() -> None:
    out, clock = io.StringIO(), Clock()
    bar = Progress(4, "tiles", stream=out, tty=True, enabled=True, clock=clock, redraw_s=1.0)
    clock.t += 0.5
    bar.update()  # first draw
    clock.t += 0.5
    bar.update()  # 0.5 s later: not redrawn
    clock.t += 0.6
    bar.update()  # redrawn
    bar.note("round 1 done")  # on a line of its own, the bar under it again
    clock.t += 0.1
    bar.update()  # complete: drawn whatever the time
    bar.close()
    text = out.getvalue()
    assert text.count("\n") == 2  # the note's line and the bar's last
    frames = [f for f in text.split("\r") if f.strip()]
    assert frames[0].startswith("tiles: [#####...............] 1/4 (25 %)")
    assert any(f.startswith("round 1 done\n") for f in frames)
    assert text.rstrip("\n").split("\r")[-1].startswith("tiles: [####################] 4/4")
    assert "2/4" not in text  # throttled


def test_off_means_no_progress_but_the_notes_still_print(monkeypatch) -> None:
    out = io.StringIO()
    bar = Progress(10, "x", stream=out, tty=False, enabled=False)
    for _ in range(10):
        bar.update()
    bar.note("a log line")
    bar.close()
    assert out.getvalue() == "a log line\n"
    monkeypatch.setenv(ENV_OFF, "1")
    assert not progress_wanted() and not Progress(3, stream=out).enabled
    monkeypatch.setenv(ENV_OFF, "0")
    assert progress_wanted() and not progress_wanted(no_progress=True)


def test_unknown_total_prints_every_every_s_without_eta() -> None:
    bar, out, clock = log_bar(None, unit="s", rate=False, every_s=5.0)
    for _ in range(12):
        clock.t += 1.0
        bar.set(clock.t - 100.0, "behind by 3")
    bar.close()
    assert out.getvalue().splitlines() == [
        "passes: 5 s, behind by 3",
        "passes: 10 s, behind by 3",
        "passes: 12 s, behind by 3",
    ]


def test_work_shorter_than_quiet_s_shows_nothing_and_longer_work_shows_after_it() -> None:
    bar, out, clock = log_bar(10, quiet_s=1.0)
    for _ in range(10):
        clock.t += 0.05
        bar.update()
    bar.close()
    assert out.getvalue() == ""
    bar, out, clock = log_bar(10, quiet_s=1.0)
    for _ in range(10):
        clock.t += 0.3
        bar.update()
    bar.close()
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("passes: 4/10 (40 %)")  # the first update after 1 s
    assert lines[-1].startswith("passes: 10/10 (100 %)")


def test_durations_read_well() -> None:
    assert [format_duration(s) for s in (0, 59.4, 60, 3599, 3600, 86399)] == [
        "0s",
        "59s",
        "1m00s",
        "59m59s",
        "1h00m",
        "23h59m",
    ]
    assert format_duration(float("inf")) == "?"


def _work(n: int, relay: Relay) -> int:
    for _ in range(n):
        relay.tick()
    relay.say(f"worker did {n}")
    return n


def test_workers_in_other_processes_report_into_the_parents_bar() -> None:
    bar, out, _clock = log_bar(30, every_pct=50)
    with bar, relayed(bar) as relay, ProcessPoolExecutor(max_workers=2) as ex:
        futs = [ex.submit(_work, n, relay) for n in (10, 20)]
        wait_relayed(futs, relay, bar, poll_s=0.05)
        assert sorted(f.result() for f in futs) == [10, 20]
        pump(relay, bar)  # nothing left: wait_relayed took it all
    assert bar.done == 30
    lines = out.getvalue().splitlines()
    assert {"worker did 10", "worker did 20"} <= set(lines)
    assert any(line.startswith("passes: 30/30 (100 %)") for line in lines)


def test_a_relay_without_a_bar_prints_its_messages_and_drops_ticks(capsys) -> None:
    off = Progress(3, enabled=False)
    with relayed(off) as relay:
        assert relay.queue is None
        relay.tick()
        relay.say("hello")
    assert capsys.readouterr().err == "hello\n"
