"""The Gymnasium views: checker, seeding, and identity with the batched core."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import amuled_ma  # noqa: F401  (registers the ids)
from amuled_ma.tasks import TASKS, make_batched
from amuled_ma.tasks.gym_env import DrivingEnv, FindMilkEnv

CASES = [
    ("amuled/FindMilk-v0", "findmilk", {}),
    ("amuled/FindMilk-v0", "findmilk", {"layout": "random"}),
    ("amuled/Driving-v0", "driving", {}),
]


@pytest.mark.parametrize(("env_id", "name", "kw"), CASES)
@pytest.mark.parametrize("render_mode", ["ansi", "rgb_array"])
def test_check_env(env_id, name, kw, render_mode):
    env = gym.make(env_id, render_mode=render_mode, **kw)
    check_env(env.unwrapped)
    env.reset(seed=0)
    frame = env.render()
    if render_mode == "ansi":
        assert isinstance(frame, str) and frame.count("\n") >= 9
    else:
        assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3


def test_every_task_id_is_registered_and_makes_its_view():
    # the built-in tasks have a view; a third-party task (smartgrid) keeps its package's own
    assert {name: task.gym_id for name, task in TASKS.items() if task.gym_id} == {
        "findmilk": "amuled/FindMilk-v0",
        "driving": "amuled/Driving-v0",
    }
    assert TASKS["smartgrid"].gym_id == ""
    for env_id, view in (("amuled/FindMilk-v0", FindMilkEnv), ("amuled/Driving-v0", DrivingEnv)):
        env = gym.make(env_id)
        assert type(env.unwrapped) is view and env.spec is not None
        assert env.spec.max_episode_steps is None  # the task's own max_steps ends an episode


@pytest.mark.parametrize(("env_id", "name", "kw", "copies", "steps"), [
    ("amuled/FindMilk-v0", "findmilk", {"shaping_coef": 1.0}, 2, 1000),
    ("amuled/FindMilk-v0", "findmilk", {"layout": "random", "shaping_coef": 0.5}, 2, 300),
    ("amuled/Driving-v0", "driving", {"shaping_coef": 0.25}, 2, 1000),
])  # fmt: skip
def test_batched_core_and_gym_views_are_identical(env_id, name, kw, copies, steps):
    """Copy i of a batched task seeded s == a Gymnasium view seeded s + i, step by step."""
    seed = 1000
    core = make_batched(name, copies, seed=seed, **kw)
    obs = core.reset()
    views = [gym.make(env_id, **kw) for _ in range(copies)]
    view_obs = [v.reset(seed=seed + i)[0] for i, v in enumerate(views)]
    for i in range(copies):
        np.testing.assert_array_equal(obs[i].numpy(), view_obs[i])
    rng = np.random.default_rng(0)
    episodes = 0
    for _ in range(steps):
        actions = rng.integers(0, core.num_actions, copies)
        obs, reward, term, trunc, info = core.step(torch.as_tensor(actions))
        for i, view in enumerate(views):
            o, r, te, tr, vinfo = view.step(int(actions[i]))
            np.testing.assert_array_equal(info["final_obs"][i].numpy(), o)
            assert r == reward[i].item()
            assert (te, tr) == (bool(term[i]), bool(trunc[i]))
            assert vinfo["r_env"] == info["r_env"][i].item()
            assert vinfo["r_shaping"] == info["r_shaping"][i].item()
            if te or tr:
                episodes += 1
                for k, v in vinfo["episode"].items():
                    assert v == info["episode"][k][i].item(), k
                o, _ = view.reset()
                np.testing.assert_array_equal(obs[i].numpy(), o)
    assert episodes > 0


def test_gym_seeding_is_reproducible():
    for env_id in ("amuled/FindMilk-v0", "amuled/Driving-v0"):
        a, b = gym.make(env_id), gym.make(env_id)
        oa, _ = a.reset(seed=5)
        ob, _ = b.reset(seed=5)
        np.testing.assert_array_equal(oa, ob)
        for t in range(100):
            ra = a.step(t % 3)
            rb = b.step(t % 3)
            np.testing.assert_array_equal(ra[0], rb[0])
            assert ra[1:4] == rb[1:4]


def test_gym_kwargs_reach_the_core():
    env = gym.make("amuled/FindMilk-v0", shaping_coef=3.0, max_steps=5, layout="paper")
    core = env.unwrapped.task
    assert (core.shaping_coef, core.max_steps, core.layout) == (3.0, 5, "paper")
    env.reset(seed=0)
    for _ in range(4):
        assert not env.step(2)[3]
    _, _, term, trunc, info = env.step(2)
    assert trunc and not term and info["episode"]["length"] == 5


def test_gym_view_prompts():
    env = gym.make("amuled/Driving-v0")
    env.reset(seed=0)
    text = env.unwrapped.state_prompt()
    assert "You are currently on lane 2." in text
    assert env.unwrapped.prompt_variables()["lane"] == 2
