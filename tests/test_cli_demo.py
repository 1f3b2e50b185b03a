"""``amuled demo``: its settings, argument handling, the no-server and no-recording paths.

The whole demo runs in ``tests/integration/test_live_demo.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from amuled_ma.beliefs.hosts import TINY_MODEL
from amuled_ma.cli import main
from amuled_ma.commands.demo import (
    DEMO_NUM_PARALLEL,
    LIVE_CLUSTERS,
    LIVE_STATES,
    demo_scenario,
)
from amuled_ma.scenario import load_scenario
from amuled_ma.scenario.overrides import parse_set


def test_demo_without_server_fails_fast_and_writes_nothing(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "demo"
    start = time.monotonic()
    code = main(["demo", "--host", "http://127.0.0.1:1", "--run-dir", str(run_dir)])
    elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert code == 1
    assert elapsed < 30.0  # no retry loop; the 5 s bound of preflight is tested with it
    assert "127.0.0.1:1" in err and "amuled ollama up" in err
    assert not run_dir.exists()


#: Each task's demo (issue 27): the authors' scenario (scenarios/<task>-authors.toml, their
#: recipe, replay of their gpt-4o-mini recording, 50 sampled episodes) with a demo-sized
#: budget, and the live leg's model and reply options.
DEMO_SETS = (
    "base.total_steps=131_072",
    "base.num_envs=64",
    "base.num_steps_per_env=32",
    # rsl-rl's base loop at the demo's budget (scenarios/<task>-demo.toml says why)
    'base.grad_clip="per_network"',
    "base.reshuffle_each_epoch=false",
    "base.bootstrap_time_outs=true",
    "finetune.iterations=100",
    "finetune.save_interval=25",
    "feedback.model=amuled-tiny",
    "feedback.concurrency=1",
    "feedback.timeout_s=600.0",
    "feedback.ollama={reasoning = false, num_predict = 128}",
)


@pytest.mark.parametrize(
    ("task", "source", "sets"),
    [
        ("driving", "driving-authors", DEMO_SETS),
        # FindMilk's demo keeps first-in-order ties (its own small base; docs/reproduction.md)
        ("findmilk", "findmilk-authors", (*DEMO_SETS, "task.options={}")),
    ],
)
def test_demo_scenario_file_holds_the_settings_the_demo_set(task, source, sets) -> None:
    """``scenarios/<task>-demo.toml`` = its source scenario with the demo's ``--set``s."""
    host = "http://127.0.0.1:5"
    expected = load_scenario(source)
    for text in (*sets, f"feedback.host={host}"):
        section, name, value = parse_set(text)
        expected = expected.replace(section, **{name: value})
    demo = demo_scenario(task, model=TINY_MODEL, host=host, private=True)
    assert demo.settings() == expected.settings()
    assert demo.name == f"{task}-demo"
    assert demo.feedback.concurrency == DEMO_NUM_PARALLEL  # the private server's slots
    file = load_scenario(f"{task}-demo")
    assert file.feedback.model == TINY_MODEL and file.feedback.host == ""
    assert file.feedback.ollama == {"reasoning": False, "num_predict": 128}


@pytest.mark.parametrize("task", ["findmilk", "driving"])
def test_demo_replays_the_authors_recording_with_their_recipe(task) -> None:
    file = load_scenario(f"{task}-demo")
    assert file.feedback.source == "replay" and file.feedback.recording == f"{task}-gpt-4o-mini"
    assert file.finetune.recipe == "authors" and file.feedback.miss_policy == "zero"
    assert file.evaluation.modes[0] == "sampled"  # the paper's figures are sampled
    assert LIVE_STATES * len(LIVE_CLUSTERS) <= 6  # a handful of live requests


def test_demo_without_the_recording_says_where_to_put_it_in_one_line(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """Offline (tests/conftest.py sets AMULED_OFFLINE): one line naming both routes."""
    monkeypatch.setenv("AMULED_RECORDINGS", str(tmp_path / "none"))
    monkeypatch.setenv("AMULED_DATA", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path)  # in no checkout: nothing beside it
    start = time.monotonic()
    code = main(["demo", "--run-dir", str(tmp_path / "demo")])
    elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert code == 2 and elapsed < 10.0
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "findmilk-gpt-4o-mini" in err and "run without it to fetch" in err
    assert "AMULED_RECORDINGS" in err and "amuled import authors" in err
    assert not (tmp_path / "demo").exists()


def test_demo_with_a_real_model_keeps_the_tasks_ollama_options_and_asks_two_at_once() -> None:
    """As before: a model other than the tiny one, on a server the demo did not start."""
    demo = demo_scenario(
        "findmilk",
        model="llama3.1:8b",
        host="http://127.0.0.1:11434",
        private=False,
        overrides=["evaluation.episodes=3"],
    )
    assert demo.feedback.model == "llama3.1:8b"
    assert demo.feedback.ollama == load_scenario("findmilk").feedback.ollama == {}
    assert demo.feedback.concurrency == 2
    assert demo.evaluation.episodes == 3  # the user's --set comes last


def test_mini_batches_of_one_transition_are_refused_with_the_keys_named(tmp_path: Path, capsys):
    """Per-mini-batch advantage normalisation of one sample is NaN: a clear error instead."""
    code = main(
        ["train", "findmilk", "--run-dir", str(tmp_path / "r"), "--no-progress",
         "--set", "base.num_envs=1", "--set", "base.num_steps_per_env=4"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    assert "num_mini_batches = 4" in err and "mini-batches of 1" in err and "[base]" in err


def test_demo_with_a_real_model_looks_at_the_default_install(monkeypatch, capsys) -> None:
    """No host and a non-tiny model: the user's own server, not a private one."""
    from amuled_ma import llm_server
    from amuled_ma.beliefs import hosts

    monkeypatch.delenv("OLLAMA_HOST", raising=False)
    monkeypatch.setattr(hosts, "DEFAULT_HOST", "http://127.0.0.1:1")
    started = []
    monkeypatch.setattr(llm_server, "up", lambda *a, **k: started.append(1))
    assert main(["demo", "--model", "llama3.1:8b"]) == 1
    assert not started
    assert "127.0.0.1:1" in capsys.readouterr().err
