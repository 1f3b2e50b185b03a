"""``amuled demo``: argument handling and the no-server path (the live run is in the README)."""

from __future__ import annotations

import time
from pathlib import Path

from amuled_ma.cli import main
from amuled_ma.commands.demo import DEMO_BUDGET


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


def test_demo_budget_keys_are_valid_scenario_overrides() -> None:
    from amuled_ma.commands._experiment import parse_override
    from amuled_ma.scenario import load_scenario

    for task, overrides in DEMO_BUDGET.items():
        scenario = load_scenario(task)
        for text in overrides:
            section, name, value = parse_override(text)
            scenario = scenario.replace(section, **{name: value})
        assert scenario.finetune.iterations == 1
        assert scenario.finetune.num_envs * scenario.finetune.num_steps_per_env == 8
        assert scenario.base.total_steps == 65_536


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
