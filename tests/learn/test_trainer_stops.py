"""A belief backend that stays down mid-run: checkpoint kept, resume command printed."""

from __future__ import annotations

from pathlib import Path

import pytest
import tiny_cli

from amuled_ma.cli import main
from amuled_ma.errors import BackendUnavailable, ScenarioError
from amuled_ma.learn.checkpoints import checkpoint_infos

# the shared tiny run, with no periodic checkpoint and rule-based beliefs
TINY = [*tiny_cli.TINY, "--set", "finetune.save_interval=100", *tiny_cli.RULES]


def test_backend_down_mid_finetune_writes_checkpoint_and_resume_command(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    from amuled_ma.learn import population as population_mod

    run_dir = tmp_path / "run"
    assert main(["train", "findmilk", "--variant", "base", "--run-dir", str(run_dir), *TINY]) == 0
    original = population_mod.PopulationTrainer.iterate
    calls = {"n": 0}

    def server_dies_in_second_iteration(self):
        calls["n"] += 1
        if calls["n"] == 2:
            raise BackendUnavailable("no Ollama server answers at http://127.0.0.1:9 (test)")
        return original(self)

    monkeypatch.setattr(
        population_mod.PopulationTrainer, "iterate", server_dies_in_second_iteration
    )
    finetune = ["finetune", "findmilk", "--feedback", "human", "--run-dir", str(run_dir), *TINY]
    assert main(finetune) == 1
    err = capsys.readouterr().err
    # save_interval is 100: the checkpoint exists only because the stop wrote it
    assert (run_dir / "finetune-human" / "model_last.pt").is_file()
    assert "stopped at iteration 1/3" in err
    assert "resume with: amuled finetune findmilk" in err and "--resume" in err
    assert "no Ollama server answers" in err

    monkeypatch.setattr(population_mod.PopulationTrainer, "iterate", original)
    assert main([*finetune, "--resume"]) == 0
    state = checkpoint_infos(run_dir / "finetune-human" / "model_last.pt")
    assert state["completed"] is True and calls["n"] == 2  # resumed with the original rollout


def test_unknown_ollama_option_is_named() -> None:
    from amuled_ma.scenario import load_scenario

    # refused when the scenario is validated, before any source is built
    with pytest.raises(ScenarioError, match=r"\[feedback.ollama\] unknown key\(s\) temprature"):
        load_scenario("findmilk").replace(
            "feedback", source="ollama", ollama={"num_predict": 64, "temprature": 0.5}
        )


@pytest.mark.parametrize("task", ["findmilk", "driving"])
def test_a_run_stopped_between_iterations_and_resumed_equals_the_run_that_never_stopped(
    tmp_path: Path, task: str
) -> None:
    """The checkpoint keeps the episodes in flight (task state, random streams, sums).

    Fine-tune 6 iterations straight, and 6 iterations stopped after the 3rd (a Ctrl-C at
    an iteration boundary, as the periodic checkpoint a killed worker leaves behind) then
    resumed: every learned figure of every iteration, and the final weights, are equal.
    The base is trained once and shared, so the two fine-tunes start from the same policy.
    """
    import json
    import shutil

    import torch

    from amuled_ma.learn import population as population_mod

    run_dir = tmp_path / "run"
    tiny = [*tiny_cli.TINY, "--set", "finetune.iterations=6", *tiny_cli.RULES]
    assert main(["train", task, "--variant", "base", "--run-dir", str(run_dir), *tiny]) == 0

    for out in ("straight", "stopped"):  # two runs on the one base
        shutil.copytree(run_dir, tmp_path / out)

    def finetune(out: str, *extra: str) -> int:
        argv = ["finetune", task, "--feedback", "amuled", "--run-dir", str(tmp_path / out)]
        return main([*argv, *tiny, *extra])

    assert finetune("straight") == 0

    def stop_after_third(member, iteration):
        if iteration == 3:
            raise KeyboardInterrupt

    original = population_mod.PopulationTrainer.__init__

    def with_stop(self, *args, **kwargs):
        original(self, *args, **kwargs)
        if self.runner.current_learning_iteration == 0:  # the first attempt, not the resume
            self.specs[0].on_iteration = stop_after_third

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(population_mod.PopulationTrainer, "__init__", with_stop)
        assert finetune("stopped") == 130  # the command line's Ctrl-C exit
        stopped = tmp_path / "stopped" / "finetune-amuled" / "model_last.pt"
        assert checkpoint_infos(stopped)["iteration"] == 3
        assert finetune("stopped", "--resume") == 0

    def learned(out: str) -> list[dict]:
        rows = json.loads((tmp_path / out / "finetune-amuled" / "curve.json").read_text())
        return [{k: v for k, v in row.items() if k != "wall_s"} for row in rows]

    assert len(learned("straight")) == 6
    assert learned("stopped") == learned("straight")
    weights = [
        torch.load(tmp_path / out / "finetune-amuled" / "model_last.pt", weights_only=True)[
            "actor_state_dict"
        ]
        for out in ("straight", "stopped")
    ]
    for name, tensor in weights[0].items():
        assert torch.equal(tensor, weights[1][name]), name
