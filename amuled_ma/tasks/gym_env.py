"""Gymnasium views of the batched tasks: one copy (``num_envs=1``), numpy in and out.

``reset(seed=s)`` makes the view copy ``i`` of a core seeded ``s - i``; ``step`` returns the
observation the step reached (``info["final_obs"]``) and Python numbers in ``info``.
"""

from __future__ import annotations

import numbers
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from amuled_ma.tasks.base import BatchedTask
from amuled_ma.tasks.driving import Driving
from amuled_ma.tasks.findmilk import FindMilk

__all__ = ["DrivingEnv", "FindMilkEnv", "TaskEnv"]


def _python(value: torch.Tensor) -> Any:
    """Return the single element of a 1-element tensor as a Python number or bool."""
    return value.reshape(-1)[0].item()


class TaskEnv(gym.Env[np.ndarray, np.int64]):
    """Single-copy Gymnasium view of a `BatchedTask`; ``task_kwargs`` go to its constructor.

    Raises:
        ValueError: Unknown ``render_mode`` or a bad task argument.
    """

    # gymnasium.Env declares metadata as an instance attribute, so no ClassVar here.
    metadata: dict[str, Any] = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}  # noqa: RUF012
    task_class: ClassVar[type[BatchedTask]]

    def __init__(self, render_mode: str | None = None, **task_kwargs: Any) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode: expected None, 'ansi' or 'rgb_array', got {render_mode!r}"
            )
        self.render_mode = render_mode
        self.task = self.task_class(1, **task_kwargs)
        self.action_space = spaces.Discrete(self.task.num_actions)
        self.observation_space = spaces.Box(
            low=np.asarray(self.task.obs_low, dtype=np.float32),
            high=np.asarray(self.task.obs_high, dtype=np.float32),
            dtype=np.float32,
        )
        self._episode_over = False
        self._started = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; a reset without a seed continues the core's streams."""
        super().reset(seed=seed)
        if seed is not None or not (self._started and self._episode_over):
            obs = self.task.reset(seed)
        else:
            obs = self.task.obs  # the core auto-reset when the last episode ended
        self._started = True
        self._episode_over = False
        return obs[0].cpu().numpy().copy(), {}

    def step(self, action: object) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Take one action; returns ``(obs, reward, terminated, truncated, info)``.

        Raises:
            ValueError: ``action`` is not an integer in the action space.
        """
        if not self._started:
            raise RuntimeError(f"{type(self).__name__}: call reset() before step()")
        a = np.asarray(action)
        if (
            a.size != 1
            or not (np.issubdtype(a.dtype, np.integer) or isinstance(action, numbers.Integral))
            or isinstance(action, bool)
            or not 0 <= int(a.reshape(-1)[0]) < self.task.num_actions
        ):
            raise ValueError(
                f"action: expected an integer in 0..{self.task.num_actions - 1} "
                f"({', '.join(self.task.action_names)}), got {action!r}"
            )
        actions = torch.tensor([int(a.reshape(-1)[0])], dtype=torch.int64, device=self.task.device)
        _, reward, terminated, truncated, tinfo = self.task.step(actions)
        term, trunc = bool(terminated[0]), bool(truncated[0])
        info = {k: _python(v) for k, v in tinfo.items() if k not in ("final_obs", "episode")}
        if term or trunc:
            info["episode"] = {k: _python(v) for k, v in tinfo["episode"].items() if k != "done"}
        self._episode_over = term or trunc
        obs = tinfo["final_obs"][0].cpu().numpy().copy()
        return obs, float(reward[0]), term, trunc, info

    def render(self) -> str | np.ndarray | None:
        """Render in ``render_mode`` (``None`` when no render mode was chosen)."""
        if self.render_mode is None:
            gym.logger.warn(
                "You are calling render method without specifying any render mode, "
                f"e.g. gymnasium.make({self.task.gym_id!r}, render_mode='ansi')"
            )
            return None
        return self.task.render(self.render_mode)

    def prompt_variables(self) -> dict[str, Any]:
        """Return the template variables of the current state prompt."""
        return self.task.prompt_variables()[0]

    def state_prompt(self) -> str:
        """Return the rendered state prompt of the current state."""
        return self.task.state_prompts()[0]


class FindMilkEnv(TaskEnv):
    """``amuled/FindMilk-v0``: see `findmilk` for the rules."""

    task_class = FindMilk


class DrivingEnv(TaskEnv):
    """``amuled/Driving-v0``: see `driving` for the rules."""

    task_class = Driving
