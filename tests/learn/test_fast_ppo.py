"""The lean rollout and PPO update reproduce rsl-rl's ``act``/``process_env_step``/``update``.

Bit for bit: the same parameters, losses, feedback diagnostics and torch random state
after several iterations, for base training on both tasks and for a fine-tune.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from amuled_ma.learn.fast_ppo import ppo_update, supports
from amuled_ma.learn.feedback import CallableFeedback
from amuled_ma.learn.trainer import LAST, Trainer
from amuled_ma.scenario import load_scenario


def _iterate(trainer: Trainer, fast: bool, iterations: int = 3):
    assert supports(trainer.alg)
    trainer.alg.train_mode()
    out = []
    for it in range(iterations):
        trainer._set_lr(it)
        extra = trainer._rollout() if fast else trainer._rollout_rsl_rl()
        losses = ppo_update(trainer.alg) if fast else trainer.alg.update()
        out.append((extra, losses, trainer.env.drain_episodes()))
    alg = trainer.alg
    params = [p.detach().clone() for p in [*alg.actor.parameters(), *alg.critic.parameters()]]
    return out, params, torch.get_rng_state(), trainer.task.obs.clone()


def _assert_same(ref, got) -> None:
    assert got[0] == ref[0]
    assert all(torch.equal(a, b) for a, b in zip(got[1], ref[1], strict=True))
    assert torch.equal(got[2], ref[2])  # the same random draws, so later rollouts match too
    assert torch.equal(got[3], ref[3])


@pytest.mark.parametrize("name", ["findmilk", "driving"])
def test_lean_base_iterations_are_bit_identical_to_rsl_rl(tmp_path, name):
    scenario = load_scenario(name).replace("output", tensorboard=False)
    ref = _iterate(Trainer(scenario, tmp_path / "ref"), fast=False)
    got = _iterate(Trainer(scenario, tmp_path / "fast"), fast=True)
    _assert_same(ref, got)


def test_lean_finetune_iterations_are_bit_identical_to_rsl_rl(tmp_path):
    scenario = load_scenario("findmilk").replace("output", tensorboard=False)
    base = Trainer(scenario.replace("base", total_steps=2 * 64 * 32), tmp_path / "base")
    base.train()

    def run(fast: bool):
        feedback = CallableFeedback(lambda obs: np.tile([0.1, 0.2, 0.3, 0.4], (len(obs), 1)))
        trainer = Trainer(
            scenario,
            tmp_path / f"ft-{fast}",
            variant="finetune:scripted",
            feedback=feedback,
            base_checkpoint=tmp_path / "base" / LAST,
        )
        return (*_iterate(trainer, fast, iterations=4), feedback.summary())

    ref, got = run(False), run(True)
    _assert_same(ref, got)
    assert got[4] == ref[4]


def test_unsupported_configuration_falls_back_to_rsl_rl(tmp_path):
    scenario = load_scenario("findmilk").replace("output", tensorboard=False)
    trainer = Trainer(scenario, tmp_path / "fallback")
    trainer.alg.use_mixed_precision = True
    assert not supports(trainer.alg)
    calls = []
    trainer.alg.update = lambda: calls.append(1) or {"value": 0.0}
    assert ppo_update(trainer.alg) == {"value": 0.0}
    assert calls == [1]
