"""``amuled demo``: argument handling and the no-server path (the live run is in the README)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from amuled_ma.beliefs.hosts import TINY_MODEL
from amuled_ma.cli import main
from amuled_ma.commands._experiment import parse_override
from amuled_ma.commands.demo import DEMO_NUM_PARALLEL, DEMO_TASKS, demo_scenario
from amuled_ma.scenario import load_scenario


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


#: What ``amuled demo`` set before its settings moved to ``scenarios/<task>-demo.toml``: the
#: ``--set`` texts of its code (``commands/demo.py`` at 1792ce5: the feedback lines,
#: ``DEMO_BUDGET``, ``TINY_REPLY``), for the tiny model on the private server.
OLD_DEMO_SETS = (
    "feedback.source=ollama",
    "feedback.model=amuled-tiny",
    "feedback.concurrency=1",
    "feedback.timeout_s=600.0",
    "base.total_steps=65_536",
    "finetune.iterations=1",
    "finetune.num_envs=4",
    "finetune.num_steps_per_env=2",
    "finetune.save_interval=1",
    "evaluation.episodes=10",
    "feedback.ollama={reasoning = false, num_predict = 128}",
)


@pytest.mark.parametrize("task", DEMO_TASKS)
def test_demo_scenario_file_holds_the_settings_the_demo_set(task: str) -> None:
    """``scenarios/<task>-demo.toml`` = the task's scenario with the demo's old ``--set``s."""
    host = "http://127.0.0.1:5"
    expected = load_scenario(task)
    for text in (*OLD_DEMO_SETS, f"feedback.host={host}"):
        section, name, value = parse_override(text)
        expected = expected.replace(section, **{name: value})
    demo = demo_scenario(task, model=TINY_MODEL, host=host, private=True)
    assert demo.settings() == expected.settings()
    assert demo.name == f"{task}-demo"
    assert demo.feedback.concurrency == DEMO_NUM_PARALLEL  # the private server's slots
    # the numbers the old demo tests checked, read from the file itself
    file = load_scenario(f"{task}-demo")
    assert file.finetune.iterations == 1 and file.base.total_steps == 65_536
    assert file.finetune.num_envs * file.finetune.num_steps_per_env == 8
    assert file.feedback.model == TINY_MODEL and file.feedback.host == ""
    assert file.feedback.ollama == {"reasoning": False, "num_predict": 128}


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
