"""A belief backend that stays down mid-run: checkpoint kept, resume command printed."""

from __future__ import annotations

from pathlib import Path

import pytest
import tiny_cli

from amuled_ma.cli import main
from amuled_ma.errors import BackendUnavailable, ScenarioError
from amuled_ma.learn.run_folder import checkpoint_state

# the shared tiny run, with no periodic checkpoint and rule-based beliefs
TINY = [*tiny_cli.TINY, "--set", "finetune.save_interval=100", *tiny_cli.RULES]


def test_backend_down_mid_finetune_writes_checkpoint_and_resume_command(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    from amuled_ma.learn import trainer as trainer_mod

    run_dir = tmp_path / "run"
    assert main(["train", "findmilk", "--variant", "base", "--run-dir", str(run_dir), *TINY]) == 0
    original = trainer_mod.Trainer._iterate
    calls = {"n": 0}

    def server_dies_in_second_iteration(self):
        calls["n"] += 1
        if calls["n"] == 2:
            raise BackendUnavailable("no Ollama server answers at http://127.0.0.1:9 (test)")
        return original(self)

    monkeypatch.setattr(trainer_mod.Trainer, "_iterate", server_dies_in_second_iteration)
    finetune = ["finetune", "findmilk", "--feedback", "human", "--run-dir", str(run_dir), *TINY]
    assert main(finetune) == 1
    err = capsys.readouterr().err
    # save_interval is 100: the checkpoint exists only because the stop wrote it
    assert (run_dir / "finetune-human" / "model_last.pt").is_file()
    assert "stopped at iteration 1/3" in err
    assert "resume with: amuled finetune findmilk" in err and "--resume" in err
    assert "no Ollama server answers" in err

    monkeypatch.setattr(trainer_mod.Trainer, "_iterate", original)
    assert main([*finetune, "--resume"]) == 0
    state = checkpoint_state(run_dir / "finetune-human" / "model_last.pt")
    assert state["completed"] is True and calls["n"] == 2  # resumed with the original rollout


def test_unknown_ollama_option_is_named() -> None:
    from amuled_ma.learn.feedback import make_source
    from amuled_ma.scenario import load_scenario

    scenario = load_scenario("findmilk").replace(
        "feedback", source="ollama", ollama={"num_predict": 64, "temprature": 0.5}
    )
    with pytest.raises(ScenarioError, match=r"\[feedback.ollama\] unknown key\(s\) temprature"):
        make_source(scenario)
