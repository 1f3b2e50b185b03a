"""Progress of a long phase: plain lines on a fake clock, and the watcher on a real one."""

from __future__ import annotations

import io
import time

from amuled_ma.monitor.progress import Progress, duration


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_plain_lines_after_10_s_then_every_30_s_with_the_eta() -> None:
    clock, out = Clock(), io.StringIO()
    progress = Progress("findmilk/amuled", 20, bar=False, clock=clock, stream=out, watch=False)
    clock.now += 9.9
    progress.update(1)  # a phase shorter than 10 s prints nothing
    assert out.getvalue() == ""
    clock.now += 0.1
    progress.update(1)  # 10 s, 2 of 20 done: 5 s each, 18 left = 90 s
    assert out.getvalue() == "findmilk/amuled: 2/20 it, 10 s elapsed, ETA 1 min 30 s\n"
    clock.now += 29.0
    assert progress.check() is False  # 29 s since the last line
    clock.now += 1.0  # 30 s of silence, though no step finished: the line comes anyway
    assert progress.check() is True
    assert (
        out.getvalue().splitlines()[-1] == "findmilk/amuled: 2/20 it, 40 s elapsed, ETA 6 min 0 s"
    )
    progress.close()


def test_a_resumed_phase_counts_the_eta_from_the_steps_done_here() -> None:
    clock, out = Clock(), io.StringIO()
    progress = Progress("evaluate", 10, bar=False, initial=6, clock=clock, stream=out, watch=False)
    clock.now += 12.0
    assert progress.check() is True
    assert out.getvalue() == "evaluate: 6/10 it, 12 s elapsed, ETA after the first step\n"
    progress.update(2)  # 2 done here in 12 s, 2 left: 12 s
    clock.now += 30.0
    progress.check()
    assert out.getvalue().splitlines()[-1] == "evaluate: 8/10 it, 42 s elapsed, ETA 42 s"
    unknown = Progress("fetch", None, bar=False, clock=clock, stream=out, watch=False)
    assert unknown.line() == "fetch: 0/? it, 0 s elapsed, ETA not known"


def test_the_watcher_writes_while_one_step_takes_long() -> None:
    """Real time, short intervals: lines come while no step finishes, none after close."""
    out = io.StringIO()
    with Progress("slow", 3, bar=False, first=0.05, every=0.1, stream=out):
        time.sleep(0.5)  # one step that takes 10 intervals
    lines = out.getvalue().splitlines()
    assert 2 <= len(lines) <= 6 and all(line.startswith("slow: 0/3 it") for line in lines)
    time.sleep(0.2)
    assert out.getvalue().splitlines() == lines


def test_held_keeps_the_lines_still_while_a_person_is_asked() -> None:
    from amuled_ma.monitor.progress import held

    clock, out = Clock(), io.StringIO()
    progress = Progress("findmilk/amuled", 4, bar=False, clock=clock, stream=out, watch=False)
    clock.now += 45.0
    with held():
        assert progress.check() is False  # due, but the question stays readable
    assert progress.check() is True
    assert out.getvalue() == "findmilk/amuled: 0/4 it, 45 s elapsed, ETA after the first step\n"


def test_plain_line_pattern_matches_the_lines_and_not_an_error() -> None:
    from amuled_ma.monitor.progress import PLAIN_LINE

    clock = Clock()
    progress = Progress("findmilk/amuled", 20, bar=False, clock=clock, watch=False)
    assert PLAIN_LINE.match(progress.line())
    assert PLAIN_LINE.match("evaluate: 1,204/2,000 policy, 2 h 4 min elapsed, ETA 3 min 0 s")
    assert not PLAIN_LINE.match("amuled: error: scenario.toml: [finetune] iterations: 0")


def test_durations() -> None:
    assert [duration(s) for s in (0.4, 59.4, 61, 3599, 3600 * 2 + 240)] == [
        "0 s", "59 s", "1 min 1 s", "59 min 59 s", "2 h 4 min",
    ]  # fmt: skip


def test_a_training_run_without_bars_prints_plain_lines(tmp_path, monkeypatch, capsys) -> None:
    """``amuled train --no-progress``, its lines due at once: one per iteration, on stderr."""
    from amuled_ma.cli import main
    from amuled_ma.monitor import progress

    monkeypatch.setattr(progress, "FIRST_LINE_S", 0.0)
    monkeypatch.setattr(progress, "PLAIN_EVERY_S", 0.0)
    argv = [
        "train", "findmilk", "--run-dir", str(tmp_path), "--no-progress",
        "--set", "base.total_steps=512", "--set", "base.num_envs=16",
        "--set", "base.num_steps_per_env=16", "--set", "output.tensorboard=false",
    ]  # fmt: skip
    assert main(argv) == 0
    lines = [
        line for line in capsys.readouterr().err.splitlines() if line.startswith("findmilk/base:")
    ]
    # 512 steps / (16 copies x 16 steps) = 2 iterations; the watcher may repeat a line
    counts = [line.split(",")[0] for line in lines]
    assert counts == sorted(counts)
    assert {"findmilk/base: 1/2 it", "findmilk/base: 2/2 it"} <= set(counts)
