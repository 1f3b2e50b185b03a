"""One job alone (a population of one): files, resume, a fine-tune's start and effect."""

import json

import numpy as np
import pytest
import torch

from amuled_ma.deliberation.feedback_base import CallableFeedback
from amuled_ma.errors import CheckpointError
from amuled_ma.learn.checkpoints import LAST
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.learn.population import PopulationTrainer
from amuled_ma.learn.population_groups import MemberSpec
from amuled_ma.records.variants import Variant


def Trainer(scenario, out_dir, **job) -> PopulationTrainer:  # noqa: N802 - the job's trainer
    """A job alone, as ``amuled train`` / ``finetune`` trains it."""
    return PopulationTrainer([MemberSpec(scenario, out_dir, **job)])


def test_base_training_writes_checkpoint_curve_and_config(tmp_path, tiny_scenario, factory):
    [out] = Trainer(tiny_scenario, tmp_path / "base", task_factory=factory).train()
    assert out.completed and out.iterations == 6 and out.env_steps == 6 * 128
    assert (tmp_path / "base" / LAST).is_file()
    curve = json.loads((tmp_path / "base" / "curve.json").read_text())
    assert len(curve) == 6 and "losses/surrogate" in curve[0]
    cfg = json.loads((tmp_path / "base" / "train_cfg.json").read_text())
    # the original config, not rsl-rl's mutated copy
    assert "multi_gpu" not in cfg
    assert cfg["actor"]["distribution_cfg"]["class_name"].endswith(":CategoricalDistribution")
    state = torch.load(tmp_path / "base" / LAST, weights_only=False)
    assert state["iter"] == 6 and state["infos"]["completed"]


def test_resume_continues_from_checkpoint(tmp_path, tiny_scenario, factory):
    calls = []

    def stop_at_3(trainer, it):
        calls.append(it)
        if it == 3:
            raise KeyboardInterrupt

    trainer = Trainer(
        tiny_scenario,
        tmp_path / "b",
        task_factory=factory,
        on_iteration=stop_at_3,
        resume_hint="amuled x",
    )
    with pytest.raises(KeyboardInterrupt):
        trainer.train()
    state = torch.load(tmp_path / "b" / LAST, weights_only=False)
    assert state["iter"] == 3 and not state["infos"]["completed"]
    resumed = Trainer(tiny_scenario, tmp_path / "b", task_factory=factory, resume=True)
    assert resumed.runner.current_learning_iteration == 3
    [out] = resumed.train()
    assert out.iterations == 6 and len(out.curve) == 6


def test_finetune_needs_base_checkpoint(tmp_path, tiny_scenario, factory):
    fb = CallableFeedback(lambda obs: np.full((len(obs), 4), 0.25))
    with pytest.raises(CheckpointError):
        Trainer(
            tiny_scenario,
            tmp_path / "ft",
            variant=Variant.finetune("x"),
            feedback=fb,
            base_checkpoint=tmp_path / "missing.pt",
            task_factory=factory,
        )


def test_finetune_moves_policy_towards_feedback_and_anchors(tmp_path, tiny_scenario, factory):
    [base] = Trainer(tiny_scenario, tmp_path / "base", task_factory=factory).train()

    def always_left(obs):
        out = np.zeros((len(obs), 4))
        out[:, 2] = 1.0
        return out

    scenario = tiny_scenario.replace("finetune", iterations=15, lambda_kl=0.0)
    fb = CallableFeedback(always_left, name="left")
    trainer = Trainer(
        scenario,
        tmp_path / "ft",
        variant=Variant.finetune("left"),
        feedback=fb,
        base_checkpoint=base.checkpoint,
        task_factory=factory,
    )
    # starts as a copy of the base policy
    base_actor = load_policy(base.checkpoint, scenario.ppo)
    obs = torch.tensor([[0.0, 0.0, 4.0, 4.0], [2.0, 2.0, 4.0, 4.0]])
    torch.testing.assert_close(
        action_log_probs(trainer.member_policy(0), obs), action_log_probs(base_actor, obs)
    )
    [out] = trainer.train()
    assert out.feedback["steps"] == 15 * 2 * 16
    assert out.feedback["unique_states"] <= 25
    p_left = action_log_probs(load_policy(out.checkpoint, scenario.ppo), obs).exp()[:, 2]
    p_left_base = action_log_probs(base_actor, obs).exp()[:, 2]
    assert torch.all(p_left > p_left_base)
    assert out.curve[-1]["feedback/feedback_reward"] > out.curve[0]["feedback/feedback_reward"]
    assert "feedback/kl" in out.curve[0]
