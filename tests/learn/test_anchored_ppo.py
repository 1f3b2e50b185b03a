"""AnchoredPPO: rsl-rl's PPO plugged in by class_name, with the KL anchor in the reward."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from lone_trainer import Trainer
from rsl_rl.algorithms import PPO

from amuled_ma.deliberation.feedback_base import CallableFeedback
from amuled_ma.learn.anchored_ppo import AnchoredPPO
from amuled_ma.learn.policies import action_log_probs

LEFT = [0.0, 0.0, 1.0, 0.0]


def fine_tune(tiny_scenario, factory, tmp_path, **finetune):
    base = Trainer(tiny_scenario, tmp_path / "base", task_factory=factory).train()
    scenario = tiny_scenario.replace("finetune", **finetune) if finetune else tiny_scenario
    feedback = CallableFeedback(lambda obs: np.tile(LEFT, (len(obs), 1)), name="left")
    return Trainer(
        scenario, tmp_path / "tune", variant="finetune:left", feedback=feedback,
        base_checkpoint=base.checkpoint, task_factory=factory,
    )  # fmt: skip


def test_rsl_rl_resolves_our_class_and_keeps_its_update(tiny_scenario, factory, tmp_path):
    trainer = Trainer(tiny_scenario, tmp_path / "base", task_factory=factory)
    assert type(trainer.alg) is AnchoredPPO and isinstance(trainer.alg, PPO)
    # the update, storage and returns are rsl-rl's own (not overridden)
    assert AnchoredPPO.compute_returns is not PPO.compute_returns  # only closes windows
    for name in ("update", "act", "process_env_step"):
        assert getattr(AnchoredPPO, name) is not getattr(PPO, name)
    for name in ("save", "load", "get_policy", "train_mode", "eval_mode"):
        assert getattr(AnchoredPPO, name) is getattr(PPO, name)
    # CleanRL's Adam
    assert trainer.alg.optimizer.param_groups[0]["eps"] == 1e-5
    assert trainer.alg.base_actor is None


def test_transition_reward_is_feedback_minus_lambda_times_per_sample_kl(
    tiny_scenario, factory, tmp_path
):
    trainer = fine_tune(tiny_scenario, factory, tmp_path, lambda_kl=2.5)
    alg, env = trainer.alg, trainer.env
    # move the policy away from the base so the anchor is not zero
    with torch.no_grad():
        for p in alg.actor.parameters():
            p.add_(0.3 * torch.randn_like(p))
    obs = env.get_observations()
    state = obs["policy"].clone()
    with torch.inference_mode():
        actions = alg.act(obs)
        index = actions.argmax(-1)
        logp = action_log_probs(alg.actor, state).gather(1, index[:, None]).squeeze(1)
        logp_base = action_log_probs(alg.base_actor, state).gather(1, index[:, None]).squeeze(1)
        _, rewards, dones, extras = env.step(actions)
        alg.process_env_step(env.get_observations(), rewards, dones, extras)
    fb = (index == 2).float()  # the feedback believes only LEFT (action 2)
    expected = fb - 2.5 * (logp - logp_base)
    timeouts = extras["time_outs"]
    stored = alg.storage.rewards[0].squeeze(-1)
    assert torch.all(timeouts == 0)  # no bootstrap term on the first step
    assert torch.allclose(stored, expected, atol=1e-6)
    assert (logp - logp_base).abs().max() > 1e-3  # the anchor really contributed
    (stats,) = alg.member_rollout_stats()
    assert stats["feedback_reward"] == pytest.approx(float(fb.mean()))
    assert stats["kl"] == pytest.approx(float((logp - logp_base).mean()), abs=1e-6)


def test_base_policy_is_frozen_and_read_without_sampling(tiny_scenario, factory, tmp_path):
    trainer = fine_tune(tiny_scenario, factory, tmp_path, lambda_kl=1.0)
    base = trainer.alg.base_actor
    assert all(not p.requires_grad for p in base.parameters())
    before = [p.clone() for p in base.parameters()]
    trainer.train()
    assert all(torch.equal(a, b) for a, b in zip(before, base.parameters(), strict=True))
    # reading a policy's probabilities draws nothing from the torch RNG
    obs = torch.zeros(3, 4)
    state = torch.get_rng_state()
    probs = action_log_probs(base, obs).exp()
    assert torch.equal(state, torch.get_rng_state())
    assert torch.allclose(probs.sum(-1), torch.ones(3))


def test_zero_lambda_fine_tune_reward_is_the_feedback(tiny_scenario, factory, tmp_path):
    trainer = fine_tune(tiny_scenario, factory, tmp_path, lambda_kl=0.0)
    out = trainer.train()
    row = out.curve[-1]
    assert 0.0 <= row["feedback/feedback_reward"] <= 1.0
    assert math.isfinite(row["feedback/kl"])
