"""The authors' CleanRL habits as ``[base]`` keys: read from a scenario file, in the trainer.

``[base].grad_clip``, ``reshuffle_each_epoch`` and ``bootstrap_time_outs`` are written in a
TOML file, loaded with :func:`load_scenario` and trained by the package's trainer
(:class:`PopulationTrainer`: one job alone on rsl-rl's classes, two as a population).
Expected values come from the definitions (CleanRL's ``clip_grad_norm_`` over both
networks; ``r`` without ``gamma * V(s)`` at a truncation), not from the code under test.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from job_settings import job_shape_of
from tensordict import TensorDict

from amuled_ma.learn.anchored_ppo import EpochShuffledStorage
from amuled_ma.learn.population import PopulationTrainer
from amuled_ma.learn.population_groups import MemberSpec
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

TINY = """
name = "tiny-base"
[task]
name = "findmilk"
seed = 3
[ppo]
hidden_dims = [8, 8]
num_mini_batches = 2
num_learning_epochs = 2
[base]
total_steps = 128
num_envs = 4
num_steps_per_env = 16
{keys}
[output]
tensorboard = false
"""


def scenario_with(tmp_path: Path, keys: str):
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "tiny-base.toml"
    path.write_text(TINY.format(keys=keys))
    return load_scenario(path)


def trainer(tmp_path: Path, keys: str, members: int = 1) -> PopulationTrainer:
    scenario = scenario_with(tmp_path, keys)
    specs = [MemberSpec(scenario, tmp_path / f"base{s}", seed=s) for s in range(members)]
    return PopulationTrainer(specs)


def test_the_defaults_are_rsl_rl_s(tmp_path):
    shape = job_shape_of(scenario_with(tmp_path, ""), Variant("base"))
    for key in ("grad_clip", "reshuffle_each_epoch", "bootstrap_time_outs"):
        assert key not in shape.cfg["algorithm"]
    alg = trainer(tmp_path, "").alg
    assert alg.grad_clip == "per_network" and alg.max_grad_norm == 0.5
    assert type(alg.storage) is not EpochShuffledStorage and alg.bootstrap_time_outs


def test_joint_clipping_reaches_the_base_optimiser(tmp_path):
    alg = trainer(tmp_path, 'grad_clip = "joint"').alg
    assert alg.max_grad_norm == math.inf and alg.joint_max_grad_norm == 0.5
    params = [*alg.actor.parameters(), *alg.critic.parameters()]
    torch.manual_seed(2)
    grads = [torch.randn_like(p) * 3 for p in params]
    for p, g in zip(params, grads, strict=True):
        p.grad = g.clone()
    # CleanRL (ppo.py:315): g * min(1, 0.5 / (||cat(actor g, critic g)|| + 1e-6))
    norm = float(torch.cat([g.flatten() for g in grads]).double().norm())
    assert norm > 0.5
    scale = min(1.0, 0.5 / (norm + 1e-6))
    alg.set_learning_rate(0.0)
    alg.optimizer.step()
    for p, g in zip(params, grads, strict=True):
        assert torch.allclose(p.grad, g * scale, rtol=1e-6, atol=1e-7)


def test_a_partition_per_epoch_reaches_the_base_storage(tmp_path):
    alone = trainer(tmp_path / "alone", "reshuffle_each_epoch = true").alg
    assert type(alone.storage) is EpochShuffledStorage
    together = trainer(tmp_path / "pop", "reshuffle_each_epoch = true", members=2).alg
    assert together.storage.reshuffle_each_epoch
    assert not trainer(tmp_path / "pop0", "", members=2).alg.storage.reshuffle_each_epoch


@pytest.mark.parametrize("bootstrap", [True, False])
def test_no_bootstrap_at_the_time_limit_reaches_the_base_update(tmp_path, bootstrap):
    alg = trainer(tmp_path, f"bootstrap_time_outs = {str(bootstrap).lower()}").alg
    assert alg.bootstrap_time_outs is bootstrap
    obs = TensorDict({"policy": torch.zeros(4, 8)}, batch_size=[4])
    with torch.inference_mode():
        alg.act(obs)
        values = alg.transition.values.squeeze(-1).clone()
        rewards = torch.tensor([1.0, 2.0, -1.0, 0.5])
        time_outs = torch.tensor([1.0, 0.0, 1.0, 0.0])
        alg.process_env_step(obs, rewards, time_outs, {"time_outs": time_outs})
    stored = alg.storage.rewards[0].squeeze(-1)
    # rsl-rl: r + gamma * V(s) on a truncated copy (gamma 0.99); CleanRL (ppo.py:230): r
    expected = rewards + (0.99 * values * time_outs if bootstrap else 0.0)
    assert torch.allclose(stored, expected)


def test_authors_scenarios_train_bases_with_the_authors_loop():
    for name in ("findmilk-authors", "driving-authors"):
        base = load_scenario(name).base
        assert (base.grad_clip, base.reshuffle_each_epoch, base.bootstrap_time_outs) == (
            "joint",
            True,
            False,
        ), name
    for name in ("findmilk", "driving"):
        base = load_scenario(name).base
        assert (base.grad_clip, base.reshuffle_each_epoch, base.bootstrap_time_outs) == (
            "per_network",
            False,
            True,
        ), name
