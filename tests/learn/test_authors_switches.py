"""The switches: each CleanRL habit of the authors' fine-tune, alone.

Joint gradient clipping, a new mini-batch partition per epoch, no bootstrap at a
truncation (``[finetune]`` keys, :mod:`amuled_ma.learn.anchored_ppo`) and FindMilk's random
tie-breaking of the nearest baby (``[task].options.tie_break``). Expected values are
computed here from their definitions, not by the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from lone_trainer import Trainer
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from amuled_ma.deliberation.feedback_base import CallableFeedback
from amuled_ma.learn.anchored_ppo import EpochShuffledStorage, clip_jointly
from amuled_ma.learn.config import rsl_rl_config
from amuled_ma.scenario import PPOConfig
from amuled_ma.tasks.findmilk import FindMilk

LEFT = [0.0, 0.0, 1.0, 0.0]


def fine_tune(tiny_scenario, factory, tmp_path, **finetune):
    base = Trainer(tiny_scenario, tmp_path / "base", task_factory=factory).train()
    scenario = tiny_scenario.replace("finetune", **finetune)
    feedback = CallableFeedback(lambda obs: np.tile(LEFT, (len(obs), 1)), name="left")
    return Trainer(
        scenario, tmp_path / "tune", variant="finetune:left", feedback=feedback,
        base_checkpoint=base.checkpoint, task_factory=factory,
    )  # fmt: skip


# ----------------------------------------------------------------------- the defaults
def test_defaults_leave_the_rsl_rl_config_as_it_was():
    cfg = rsl_rl_config(PPOConfig(), num_steps_per_env=8)
    for key in ("grad_clip", "reshuffle_each_epoch", "bootstrap_time_outs"):
        assert key not in cfg["algorithm"]
    same = rsl_rl_config(
        PPOConfig(), num_steps_per_env=8, grad_clip="per_network",
        reshuffle_each_epoch=False, bootstrap_time_outs=True,
    )  # fmt: skip
    assert same == cfg
    with pytest.raises(TypeError, match="unknown PPO option"):
        rsl_rl_config(PPOConfig(), num_steps_per_env=8, clip_jointly=True)


def test_default_fine_tune_keeps_rsl_rl_storage_and_clipping(tiny_scenario, factory, tmp_path):
    alg = fine_tune(tiny_scenario, factory, tmp_path).alg
    assert type(alg.storage) is RolloutStorage
    assert alg.max_grad_norm == 0.5 and alg.grad_clip == "per_network"
    assert alg.joint_max_grad_norm is None and alg.bootstrap_time_outs


# ----------------------------------------------------------------------- joint clipping
def test_clip_jointly_equals_one_norm_over_the_concatenated_gradients():
    torch.manual_seed(0)
    actor, critic = torch.nn.Linear(3, 4), torch.nn.Linear(3, 1)
    params = [*actor.parameters(), *critic.parameters()]
    optimizer = torch.optim.SGD(params, lr=0.0)
    clip_jointly(optimizer, 0.5)
    grads = [torch.randn_like(p) * 3 for p in params]
    for p, g in zip(params, grads, strict=True):
        p.grad = g.clone()
    # CleanRL: g * min(1, 0.5 / (||cat(g)|| + 1e-6)), one norm over actor and critic
    norm = float(torch.cat([g.flatten() for g in grads]).double().norm())
    assert norm > 0.5  # the case that clips
    scale = min(1.0, 0.5 / (norm + 1e-6))
    optimizer.step()
    for p, g in zip(params, grads, strict=True):
        assert torch.allclose(p.grad, g * scale, rtol=1e-6, atol=1e-7)
    # the actor's part alone is scaled by the joint factor, not to its own 0.5
    actor_norm = float(torch.cat([p.grad.flatten() for p in actor.parameters()]).norm())
    assert actor_norm < 0.5 * 0.999
    with pytest.raises(ValueError, match="max_norm"):
        clip_jointly(optimizer, math.inf)


def test_an_infinite_rsl_rl_clip_leaves_gradients_bit_exact():
    torch.manual_seed(1)
    params = [torch.nn.Parameter(torch.randn(5, 3)), torch.nn.Parameter(torch.randn(3))]
    for p in params:
        p.grad = torch.randn_like(p) * 100
    before = [p.grad.clone() for p in params]
    torch.nn.utils.clip_grad_norm_(params, math.inf)
    assert all(torch.equal(p.grad, b) for p, b in zip(params, before, strict=True))


def test_joint_clip_in_the_fine_tune_optimiser(tiny_scenario, factory, tmp_path):
    alg = fine_tune(tiny_scenario, factory, tmp_path, grad_clip="joint").alg
    assert alg.max_grad_norm == math.inf  # rsl-rl's two clips multiply by 1
    assert alg.joint_max_grad_norm == 0.5  # [ppo].max_grad_norm, over both networks
    params = [*alg.actor.parameters(), *alg.critic.parameters()]
    torch.manual_seed(2)
    grads = [torch.randn_like(p) for p in params]
    for p, g in zip(params, grads, strict=True):
        p.grad = g.clone()
    norm = float(torch.cat([g.flatten() for g in grads]).double().norm())
    scale = min(1.0, 0.5 / (norm + 1e-6))
    alg.set_learning_rate(0.0)  # Adam with lr 0 keeps the weights; the hook still clips
    alg.optimizer.step()
    for p, g in zip(params, grads, strict=True):
        assert torch.allclose(p.grad, g * scale, rtol=1e-6, atol=1e-7)
    # and a real update runs with it
    trainer = fine_tune(tiny_scenario, factory, tmp_path / "again", grad_clip="joint")
    assert trainer.train().completed


# ----------------------------------------------------------------------- mini-batches
def filled_storage(cls, num_envs=2, steps=16):
    """A storage whose observation of transition ``t`` of copy ``e`` is ``t * num_envs + e``."""
    obs = TensorDict({"policy": torch.zeros(num_envs, 1)}, batch_size=[num_envs])
    storage = cls("rl", num_envs, steps, obs, [1])
    for t in range(steps):
        tr = RolloutStorage.Transition()
        ids = torch.arange(num_envs, dtype=torch.float32) + t * num_envs
        tr.observations = TensorDict({"policy": ids[:, None]}, batch_size=[num_envs])
        tr.actions = torch.zeros(num_envs, 1)
        tr.rewards = torch.zeros(num_envs)
        tr.dones = torch.zeros(num_envs)
        tr.values = torch.zeros(num_envs, 1)
        tr.actions_log_prob = torch.zeros(num_envs)
        tr.distribution_params = (torch.zeros(num_envs, 4),)
        tr.hidden_states = (None, None)
        storage.add_transition(tr)
    return storage


def epochs_of(storage, mini_batches=4, epochs=8):
    """The mini-batches of each epoch, as sets of transition ids."""
    batches = [
        frozenset(b.observations["policy"].flatten().long().tolist())
        for b in storage.mini_batch_generator(mini_batches, epochs)
    ]
    return [batches[i * mini_batches : (i + 1) * mini_batches] for i in range(epochs)]


def test_rsl_rl_reuses_one_partition_for_every_epoch():
    torch.manual_seed(3)
    epochs = epochs_of(filled_storage(RolloutStorage))
    assert all(e == epochs[0] for e in epochs)  # the same 4 mini-batches, same order


def test_epoch_shuffled_storage_draws_a_new_partition_per_epoch():
    torch.manual_seed(3)
    epochs = epochs_of(filled_storage(EpochShuffledStorage))
    assert len(epochs) == 8
    for batches in epochs:  # each epoch: 4 mini-batches of 8 covering all 32 once
        assert [len(b) for b in batches] == [8, 8, 8, 8]
        assert sorted(i for b in batches for i in b) == list(range(32))
    partitions = {frozenset(batches) for batches in epochs}
    assert len(partitions) == 8  # 8 different partitions (a repeat has odds ~1e-6)


def test_fine_tune_with_reshuffle_uses_the_storage(tiny_scenario, factory, tmp_path):
    trainer = fine_tune(tiny_scenario, factory, tmp_path, reshuffle_each_epoch=True)
    storage = trainer.alg.storage
    assert type(storage) is EpochShuffledStorage
    assert storage.num_envs == 2 and storage.num_transitions_per_env == 16
    assert trainer.train().completed


# ----------------------------------------------------------------------- time-outs
@pytest.mark.parametrize("bootstrap", [True, False])
def test_bootstrap_at_time_outs_is_a_switch(tiny_scenario, factory, tmp_path, bootstrap):
    alg = fine_tune(
        tiny_scenario, factory, tmp_path, lambda_kl=0.0, bootstrap_time_outs=bootstrap
    ).alg
    obs = TensorDict({"policy": torch.zeros(2, 4)}, batch_size=[2])
    with torch.inference_mode():
        alg.act(obs)
        values = alg.transition.values.squeeze(-1).clone()
        rewards = torch.tensor([1.0, 2.0])
        extras = {"time_outs": torch.tensor([1.0, 0.0])}
        alg.process_env_step(obs, rewards, torch.tensor([1.0, 0.0]), extras)
    stored = alg.storage.rewards[0].squeeze(-1)
    # rsl-rl: r + gamma * V(s) on the truncated copy; CleanRL: r
    expected = rewards + (0.99 * values * torch.tensor([1.0, 0.0]) if bootstrap else 0.0)
    assert torch.allclose(stored, expected)
    assert "time_outs" in extras  # the caller's dict is left as it was


# ----------------------------------------------------------------------- tie-breaking
# From (0, 0) the moves right, right, right, up, up, right lead to (4, 2) without touching a
# baby. There the crying babies at (2, 2) and (4, 4) are both at squared distance 4 (the
# next, (2, 3), at 5); the nearest sleeping baby, (3, 3), is unique (2; then (4, 0) at 4).
PATH = (3, 3, 3, 0, 0, 3)


def walk(task):
    task.reset()
    for action in PATH:
        obs, *_ = task.step(torch.full((task.num_envs,), action))
    return obs


def test_first_tie_break_shows_the_first_baby_in_xy_order():
    obs = walk(FindMilk(64, seed=5))
    assert torch.all(obs[:, :2] == torch.tensor([4.0, 2.0]))
    assert torch.all(obs[:, 4:6] == torch.tensor([2.0, 2.0]))
    assert torch.all(obs[:, 6:8] == torch.tensor([3.0, 3.0]))


def test_random_tie_break_shows_either_tied_baby_drawn_from_the_copies_generators():
    task = FindMilk(200, seed=5, tie_break="random")
    seen = []
    for _ in range(3):  # three resets, each copy drawing from its own stream
        obs = walk(task)
        assert torch.all(obs[:, :2] == torch.tensor([4.0, 2.0]))
        assert torch.all(obs[:, 6:8] == torch.tensor([3.0, 3.0]))  # no tie: always (3, 3)
        seen.append(obs[:, 4:6])
    cry = torch.cat(seen)
    first = (cry == torch.tensor([2.0, 2.0])).all(1)
    other = (cry == torch.tensor([4.0, 4.0])).all(1)
    assert torch.all(first | other)  # only the two tied babies
    # each is equally likely: 600 draws, 300 expected, 5 standard deviations is 61
    assert abs(int(first.sum()) - 300) < 61
    # the draws come from the seeded generators: the same seed, the same babies
    again = FindMilk(200, seed=5, tie_break="random")
    assert torch.equal(walk(again)[:, 4:6], seen[0])


def test_random_tie_break_without_a_tie_is_the_first_rule():
    # along the whole path the two rules agree wherever the nearest baby is unique
    first, rand = FindMilk(1, seed=0), FindMilk(1, seed=0, tie_break="random")
    for task in (first, rand):
        task.reset()
    for action in (3, 3, 3, 0, 0):  # (1,0), (2,0), (3,0), (3,1), (3,2): no tie on the way
        a = torch.tensor([action])
        assert torch.equal(first.step(a)[0], rand.step(a)[0])
    with pytest.raises(ValueError, match="tie_break"):
        FindMilk(1, tie_break="shuffle")
