"""One MDP: the PettingZoo view and the learner's VecEnv reward through one function."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from amuled_ma.deliberation import DeliberationEnv
from amuled_ma.deliberation import mdp as mdp_module
from amuled_ma.deliberation.mdp import BatchedDeliberation, actor_reward
from amuled_ma.fusion import fuse
from amuled_ma.learn.vecenv import DeliberationVecEnv
from amuled_ma.tasks import make_batched

CLUSTERS = ("consequentialist", "deontological", "virtue", "care", "social_justice")


def cluster_beliefs(obs: np.ndarray, num_actions: int) -> np.ndarray:
    """Five different, state-dependent beliefs ``[K, A]`` (a stand-in panel, deterministic)."""
    rows = []
    for k in range(len(CLUSTERS)):
        logits = np.cos(np.arange(num_actions) * (k + 1) + float(np.sum(obs)) * 0.1)
        p = np.exp(logits)
        rows.append(p / p.sum())
    return np.asarray(rows)


def panel_feedback(obs: torch.Tensor, task) -> np.ndarray:
    """The learner's feedback: the same beliefs, fused by the same arbiter (``bjs-dst``)."""
    out = []
    for row in obs.numpy():
        out.append(fuse(cluster_beliefs(row, task.num_actions), "bjs-dst"))
    return np.asarray(out)


@pytest.mark.parametrize(("task_name", "weight"), [("findmilk", 1.0), ("driving", 0.5)])
def test_pettingzoo_and_learner_rewards_agree_on_the_same_states(task_name, weight):
    env = DeliberationEnv(task_name, clusters=list(CLUSTERS), r_env_weight=weight, max_steps=40)
    learner = DeliberationVecEnv(
        BatchedDeliberation(
            make_batched(task_name, 1, seed=7, max_steps=40),
            panel_feedback,
            task_weight=weight,
            feedback_coef=1.0,
        )
    )
    learner.mdp.reset(seed=7)
    observations, _ = env.reset(seed=7)
    rng = np.random.default_rng(3)
    compared = 0
    for _ in range(120):
        state = observations["actor"]
        assert np.array_equal(state, learner.obs[0].numpy())  # the same state
        action = int(rng.integers(env.action_space("actor").n))
        beliefs = cluster_beliefs(state, len(env.action_names))
        actions = {"actor": action, **dict(zip(CLUSTERS, beliefs, strict=True))}
        observations, rewards, term, trunc, infos = env.step(actions)
        _, reward, dones, extras = learner.step(torch.tensor([action]))
        # hand-computed from the env's own parts: weight * r_task + fused[a]
        info = infos["actor"]
        expected = weight * info["r_env"] + info["fused"][action]  # shaping_coef is 0
        assert rewards["actor"] == pytest.approx(expected, abs=1e-12)
        assert float(reward[0]) == pytest.approx(rewards["actor"], abs=1e-6)
        assert float(extras["feedback"][0]) == pytest.approx(info["r_feedback"], abs=1e-6)
        compared += 1
        if term["actor"] or trunc["actor"]:
            assert bool(dones[0])
            observations, _ = env.reset(seed=compared)
            learner.mdp.reset(seed=compared)
    assert compared == 120


def test_both_views_call_the_one_reward_function(monkeypatch):
    calls = []

    def marked(r_task, fused_taken, *, task_weight, feedback_coef):
        calls.append(task_weight)
        return actor_reward(r_task, fused_taken, task_weight=task_weight, feedback_coef=0.0) + 42

    monkeypatch.setattr(mdp_module, "actor_reward", marked)
    env = DeliberationEnv("findmilk", r_env_weight=0.25)
    env.reset(seed=1)
    _, rewards, _, _, infos = env.step({"actor": 0})
    learner = DeliberationVecEnv(
        BatchedDeliberation(make_batched("findmilk", 3, seed=1), panel_feedback, task_weight=0.75)
    )
    _, reward, _, extras = learner.step(torch.zeros(3, dtype=torch.long))
    assert calls == [0.25, 0.75]
    assert rewards["actor"] == pytest.approx(0.25 * infos["actor"]["r_env"] + 42)
    r_env = torch.as_tensor(extras["info"]["r_env"], dtype=torch.float32)
    assert torch.allclose(reward, 0.75 * r_env + 42)


def test_actor_reward_hand_computed():
    r_task = torch.tensor([1.0, -0.5, 0.0])
    fused = torch.tensor([0.2, 0.9, 0.25])
    out = actor_reward(r_task, fused, task_weight=0.5, feedback_coef=2.0)
    assert torch.allclose(out, torch.tensor([0.5 + 0.4, -0.25 + 1.8, 0.5]))
    assert torch.equal(actor_reward(r_task, None, task_weight=1.0, feedback_coef=2.0), r_task)
