"""The lean PPO update reproduces rsl-rl's ``PPO.update`` bit for bit."""

from __future__ import annotations

import pytest
import torch

from amuled_ma.learn.fast_ppo import ppo_update, supports
from amuled_ma.learn.trainer import Trainer
from amuled_ma.scenario import load_scenario


def _train(tmp_path, name: str, fast: bool, iterations: int = 3):
    scenario = load_scenario(name).replace("output", tensorboard=False)
    trainer = Trainer(scenario, tmp_path / f"{name}-{fast}")
    assert supports(trainer.alg)
    trainer.alg.train_mode()
    losses = []
    for it in range(iterations):
        trainer._set_lr(it)
        trainer._rollout()
        losses.append(ppo_update(trainer.alg) if fast else trainer.alg.update())
    alg = trainer.alg
    params = [p.detach().clone() for p in [*alg.actor.parameters(), *alg.critic.parameters()]]
    return losses, params, torch.get_rng_state()


@pytest.mark.parametrize("name", ["findmilk", "driving"])
def test_lean_update_is_bit_identical_to_rsl_rl(tmp_path, name):
    ref_losses, ref_params, ref_rng = _train(tmp_path, name, fast=False)
    losses, params, rng = _train(tmp_path, name, fast=True)
    assert losses == ref_losses
    assert all(torch.equal(a, b) for a, b in zip(params, ref_params, strict=True))
    assert torch.equal(rng, ref_rng)  # the same random draws, so later rollouts match too


def test_unsupported_configuration_falls_back_to_rsl_rl(tmp_path):
    scenario = load_scenario("findmilk").replace("output", tensorboard=False)
    trainer = Trainer(scenario, tmp_path / "fallback")
    trainer.alg.use_mixed_precision = True
    assert not supports(trainer.alg)
    calls = []
    trainer.alg.update = lambda: calls.append(1) or {"value": 0.0}
    assert ppo_update(trainer.alg) == {"value": 0.0}
    assert calls == [1]
