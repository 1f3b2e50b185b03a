"""Bad input: a clear ValueError naming the argument, never a silent clip."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import amuled_ma  # noqa: F401
from amuled_ma.tasks import TASKS, get_task, make_batched
from amuled_ma.tasks.gym_env import DrivingEnv
from amuled_ma.tasks.names import BUILTIN_TASKS, TASK_NAMES


@pytest.mark.parametrize("name", ["findmilk", "driving"])
def test_bad_actions(name):
    task = make_batched(name, 3, seed=0)
    task.reset()
    n = task.num_actions
    for bad in (torch.tensor([0, n, 0]), torch.tensor([0, -1, 0])):
        with pytest.raises(ValueError, match=r"actions: every action must be in 0\.\."):
            task.step(bad)
    with pytest.raises(ValueError, match="actions: expected shape"):
        task.step(torch.zeros(4, dtype=torch.int64))
    with pytest.raises(ValueError, match="actions: expected shape"):
        task.step(torch.zeros(3, 1, dtype=torch.int64))
    with pytest.raises(ValueError, match="actions: expected an integer"):
        task.step(torch.zeros(3))
    with pytest.raises(ValueError, match="actions: expected a torch"):
        task.step([0, 0, 0])
    task.step(torch.zeros(3, dtype=torch.int32))  # any integer dtype is fine


@pytest.mark.parametrize("name", ["findmilk", "driving"])
def test_bad_constructor_arguments(name):
    cls = get_task(name)
    with pytest.raises(ValueError, match="shaping_coef"):
        cls(1, shaping_coef=-0.1)
    with pytest.raises(ValueError, match="shaping_coef"):
        cls(1, shaping_coef=float("nan"))
    with pytest.raises(ValueError, match="num_envs"):
        cls(0)
    with pytest.raises(ValueError, match="max_steps"):
        cls(1, max_steps=0)
    with pytest.raises(ValueError, match="seed"):
        cls(1, seed=-3)
    with pytest.raises(ValueError, match="seed"):
        cls(1).reset(seed=1.5)
    with pytest.raises(TypeError):
        cls(1, colour="red")


def test_bad_task_options():
    with pytest.raises(ValueError, match="layout"):
        get_task("findmilk")(1, layout="maze")
    with pytest.raises(ValueError, match="p_car"):
        get_task("driving")(1, p_car=1.5)
    with pytest.raises(ValueError, match="layout"):
        gym.make("amuled/FindMilk-v0", layout="maze")
    with pytest.raises(ValueError, match="shaping_coef"):
        gym.make("amuled/Driving-v0", shaping_coef=-1)


def test_bad_gym_actions_and_modes():
    env = gym.make("amuled/FindMilk-v0").unwrapped
    env.reset(seed=0)
    for bad in (4, -1, 1.5, "up", True, np.array([1, 2])):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    env.step(np.int64(1))
    with pytest.raises(ValueError, match="render_mode"):
        DrivingEnv(render_mode="human")  # (gym.make would wrap it in HumanRendering)
    with pytest.raises(RuntimeError, match="reset"):
        gym.make("amuled/Driving-v0").unwrapped.step(0)


def test_step_before_reset_and_render_arguments():
    task = make_batched("driving", 2)
    with pytest.raises(RuntimeError, match="reset"):
        task.step(torch.zeros(2, dtype=torch.int64))
    task.reset(seed=1)
    with pytest.raises(ValueError, match="mode"):
        task.render("human")
    with pytest.raises(ValueError, match="env_id"):
        task.render("ansi", env_id=2)


def test_registry():
    assert TASK_NAMES == ("findmilk", "driving")
    assert tuple(TASKS)[:3] == BUILTIN_TASKS == ("findmilk", "driving", "smartgrid")
    assert get_task("amuled/FindMilk-v0") is TASKS["findmilk"]
    assert get_task("DRIVING").name == "driving"
    with pytest.raises(ValueError, match="unknown task"):
        get_task("chess")
    task = make_batched("findmilk", 4, seed=0, shaping_coef=1.0)
    assert (task.num_envs, task.num_actions, task.obs_dim) == (4, 4, 8)
    assert get_task("driving").action_names == ("straight", "right", "left")
    assert make_batched("driving").obs_dim == 11


def test_registration_prompts_and_human_do_not_import_torch():
    import subprocess
    import sys

    code = (
        "import sys, gymnasium, amuled_ma, amuled_ma.tasks.prompts, amuled_ma.tasks.human; "
        "assert 'amuled/Driving-v0' in gymnasium.registry; print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
