"""Base class of the batched task environments (many copies stepped by tensor operations).

The step contract and the seeding rule: docs/tasks.md, "The batched core".
"""

from __future__ import annotations

import abc
import math
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from amuled_ma.tasks import rng

__all__ = ["BatchedTask", "check_int"]


def check_int(value: object, name: str, low: int = 0, high: int | None = None) -> int:
    """``value`` as an ``int`` in ``low..high`` (None: no top; a bool is refused).

    Raises:
        ValueError: It is not, naming ``name``.
    """
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        number = int(value)
        if low <= number and (high is None or number <= high):
            return number
    wanted = {0: "a non-negative integer", 1: "a positive integer"}.get(low, f"an integer >= {low}")
    if high is not None:
        wanted = f"an integer in {low}..{high}"
    raise ValueError(f"{name}: expected {wanted}, got {value!r}")


def paint_cells(
    rows: Sequence[Sequence[str]],
    colours: Mapping[str, tuple[int, int, int]],
    cell: int,
    background: int,
) -> np.ndarray:
    """Draw a character grid (top row first) as an RGB image: one padded square per non-``.``.

    Returns:
        ``uint8`` array ``[len(rows) * cell, len(rows[0]) * cell, 3]``.
    """
    img = np.full((len(rows) * cell, len(rows[0]) * cell, 3), background, dtype=np.uint8)
    pad = max(1, cell // 8)
    for r, row in enumerate(rows):
        for c, ch in enumerate(row):
            if ch != ".":
                img[r * cell + pad : (r + 1) * cell - pad,
                    c * cell + pad : (c + 1) * cell - pad] = colours[ch]  # fmt: skip
    return img


class BatchedTask(abc.ABC):
    """``num_envs`` copies of one task, stepped together with torch tensor operations.

    Subclasses implement `_advance`, `_reset_where`, `_observe` and `_init_task` (options as its
    keyword defaults) and set ``name`` (the key of `TASKS` and of ``prompts/tasks/<name>.md``),
    ``default_max_steps`` and the attributes docs/tasks.md tables (``obs_names``, ...).
    """

    name: ClassVar[str]
    gym_id: ClassVar[str]
    action_names: ClassVar[tuple[str, ...]]
    obs_names: ClassVar[tuple[str, ...]]
    obs_low: ClassVar[tuple[float, ...]]
    obs_high: ClassVar[tuple[float, ...]]
    metric_names: ClassVar[tuple[str, ...]]
    prompt_template: ClassVar[Path | None] = None
    judge_names: ClassVar[tuple[str, ...]] = ()
    human_feedback: ClassVar[bool] = False
    default_max_steps: ClassVar[int] = 300

    def __init__(
        self,
        num_envs: int = 1,
        *,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        shaping_coef: float = 0.0,
        max_steps: int | None = None,
        **task_options: Any,
    ) -> None:
        """Create ``num_envs >= 1`` copies (call `reset` before the first step).

        ``seed`` is the first `reset`'s base seed (None: OS entropy); ``shaping_coef`` is ``c >= 0``
        of ``reward = r_env + c * r_shaping``; ``max_steps`` None is ``default_max_steps``;
        ``task_options`` go to `_init_task` (an unknown one: TypeError).

        Raises:
            ValueError: An argument is out of range; the message names it.
        """
        self.num_envs = check_int(num_envs, "num_envs", 1)
        steps = self.default_max_steps if max_steps is None else max_steps
        self.max_steps = check_int(steps, "max_steps", 1)
        coef: object = shaping_coef
        if isinstance(coef, bool) or not (
            isinstance(coef, numbers.Real) and 0 <= float(coef) < math.inf
        ):
            raise ValueError(f"shaping_coef: expected a finite non-negative number, got {coef!r}")
        self.shaping_coef = float(coef)
        self.device = torch.device(device)
        self._seed = None if seed is None else check_int(seed, "seed")
        n, dev = self.num_envs, self.device
        self._keys: torch.Tensor | None = None
        self._ctr = torch.zeros(n, dtype=torch.int64, device=dev)
        self._t = torch.zeros(n, dtype=torch.int64, device=dev)
        self._ret = torch.zeros(n, dtype=torch.float32, device=dev)
        self._ret_env = torch.zeros(n, dtype=torch.float32, device=dev)
        self._ret_shaping = torch.zeros(n, dtype=torch.float32, device=dev)
        self._metrics = {
            k: torch.zeros(n, dtype=torch.int64, device=dev) for k in self.metric_names
        }
        self._obs: torch.Tensor | None = None
        self._initial_obs: torch.Tensor | None = None  # set: every reset copy observes it
        self._init_task(**task_options)

    @property
    def num_actions(self) -> int:
        """Number of discrete actions."""
        return len(self.action_names)

    @property
    def obs_dim(self) -> int:
        """Length of one observation vector."""
        return len(self.obs_names)

    @property
    def obs(self) -> torch.Tensor:
        """The current observation ``[num_envs, obs_dim]`` (after the last reset or step)."""
        if self._obs is None:
            raise RuntimeError(f"{type(self).__name__}: call reset() before reading obs")
        return self._obs

    @property
    def episode_steps(self) -> torch.Tensor:
        """Steps taken so far in the current episode of each copy (int64 ``[num_envs]``)."""
        return self._t

    def state_dict(self) -> dict[str, Any]:
        """Every tensor of the copies' state, cloned (``"_metrics"``: its dict of tensors)."""
        state: dict[str, Any] = {
            name: value.clone() for name, value in vars(self).items() if torch.is_tensor(value)
        }
        state["_metrics"] = {k: v.clone() for k, v in self._metrics.items()}
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` of a task built with the same settings.

        Raises:
            ValueError: A tensor is missing or has another shape, naming it.
        """
        mine = self.state_dict()
        for name, value in mine.items():
            saved = state.get(name)
            if name == "_metrics":
                if not isinstance(saved, dict) or set(saved) != set(value):
                    raise ValueError(f"task state: episode metrics {sorted(value)} expected")
                self._metrics = {k: saved[k].to(self.device).clone() for k in value}
                continue
            if not torch.is_tensor(saved) or saved.shape != value.shape:
                found = tuple(saved.shape) if torch.is_tensor(saved) else type(saved).__name__
                raise ValueError(
                    f"task state: {name} of shape {tuple(value.shape)} expected, found {found}"
                )
            setattr(self, name, saved.to(self.device).clone())

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every copy; return float32 ``[num_envs, obs_dim]`` (``seed`` None: same streams).

        Raises:
            ValueError: ``seed`` is negative or not an integer.
        """
        seed = None if seed is None else check_int(seed, "seed")
        if seed is None and self._keys is None:
            seed = self._seed if self._seed is not None else rng.entropy_seed()
        if seed is not None:
            self._keys = rng.copy_keys(seed, self.num_envs, self.device)
            self._ctr.zero_()
        everyone = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        self._reset_where(everyone)
        totals = (self._t, self._ret, self._ret_env, self._ret_shaping, *self._metrics.values())
        for value in totals:
            value.zero_()
        self._obs = self._observe()
        return self._obs

    def step(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """Advance every copy by one step (action ids ``[num_envs]``), auto-resetting finished ones.

        Returns ``(obs, reward, terminated, truncated, info)`` as docs/tasks.md describes.

        Raises:
            ValueError: ``actions`` has the wrong shape or type, or a value outside
                ``0..num_actions-1``.
            RuntimeError: `reset` was never called.
        """
        if self._obs is None:
            raise RuntimeError(f"{type(self).__name__}: call reset() before step()")
        actions = self._check_actions(actions)
        r_env, r_shaping, terminated, events = self._advance(actions)
        t = self._t + 1
        truncated = (t >= self.max_steps) & ~terminated
        done = terminated | truncated
        reward = r_env + self.shaping_coef * r_shaping if self.shaping_coef else r_env.clone()
        ret = self._ret + reward
        ret_env = self._ret_env + r_env
        ret_shaping = self._ret_shaping + r_shaping
        metrics = {k: v + events[k] for k, v in self._metrics.items()}
        final_obs = self._observe()
        episode: dict[str, torch.Tensor] = {
            "done": done,
            "return": ret,
            "return_env": ret_env,
            "return_shaping": ret_shaping,
            "length": t,
            **metrics,
        }
        self._episode_extras(episode)
        keep = ~done
        self._t = t * keep
        self._ret = ret * keep
        self._ret_env = ret_env * keep
        self._ret_shaping = ret_shaping * keep
        self._metrics = {k: v * keep for k, v in metrics.items()}
        self._reset_where(done)
        fresh = self._observe() if self._initial_obs is None else self._initial_obs
        obs = self._obs = torch.where(done[:, None], fresh, final_obs)
        info: dict[str, Any] = {
            "r_env": r_env,
            "r_shaping": r_shaping,
            "final_obs": final_obs,
            "episode": episode,
        }
        info.update(events)
        return obs, reward, terminated, truncated, info

    def prompt_variables(self, env_ids: object = None) -> list[dict[str, Any]]:
        """Return the state prompt's template variables of each selected copy (None: all)."""
        ids = self._env_ids(env_ids)
        obs = self.obs[ids].cpu().numpy()
        extras = self._prompt_extras(ids)
        return [self.prompt_variables_from_obs(o, **e) for o, e in zip(obs, extras, strict=True)]

    def state_prompts(self, env_ids: object = None) -> list[str]:
        """Return the rendered state prompt of each selected copy."""
        from amuled_ma.tasks.prompts import render_state_prompt

        return [render_state_prompt(self.name, v) for v in self.prompt_variables(env_ids)]

    @classmethod
    @abc.abstractmethod
    def prompt_variables_from_obs(cls, obs: np.ndarray, **extra: Any) -> dict[str, Any]:
        """Return the prompt variables of one observation (plus task-specific extras)."""

    @classmethod
    def _obs_values(cls, obs: np.ndarray) -> np.ndarray:
        """One observation as float64 ``[obs_dim]``; ValueError naming its shape otherwise."""
        values = np.asarray(obs, dtype=np.float64).reshape(-1)
        if values.shape != (len(cls.obs_names),):
            raise ValueError(
                f"obs: expected {len(cls.obs_names)} numbers, got shape {np.shape(obs)}"
            )
        return values

    @classmethod
    def judge_scores(cls, judge: str, obs: np.ndarray) -> np.ndarray:
        """The task's judge of a value (``policy = "judge:<name>"``): scores ``[A]`` or ``[B, A]``.

        Raises:
            ValueError: The task has no judge of that name.
        """
        known = ", ".join(cls.judge_names) or "none"
        raise ValueError(f"judge: task {cls.name!r} has no judge {judge!r} (its judges: {known})")

    def render(self, mode: str = "ansi", env_id: int = 0) -> str | np.ndarray:
        """Render copy ``env_id`` as ``"ansi"`` text or an ``"rgb_array"`` (uint8 ``[H, W, 3]``).

        Raises:
            ValueError: Unknown ``mode`` or ``env_id`` out of range.
        """
        env_id = self._env_id(env_id)
        if mode == "ansi":
            return self.render_ansi(env_id)
        if mode == "rgb_array":
            return self.render_rgb(env_id)
        raise ValueError(f"mode: expected 'ansi' or 'rgb_array', got {mode!r}")

    @abc.abstractmethod
    def render_ansi(self, env_id: int = 0) -> str:
        """Return a text picture of copy ``env_id``."""

    @abc.abstractmethod
    def render_rgb(self, env_id: int = 0, cell: int = 32) -> np.ndarray:
        """Return an RGB picture (uint8 ``[H, W, 3]``) of copy ``env_id``."""

    def _init_task(self, *args: Any, **task_options: Any) -> None:
        """Create the task state tensors; a subclass's keyword defaults are its options."""
        if args or task_options:
            raise TypeError(f"{type(self).__name__}: unexpected option(s) {sorted(task_options)}")

    @abc.abstractmethod
    def _advance(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Apply one step to every copy: ``(r_env, r_shaping, terminated, events)``.

        ``events``: ``[num_envs]`` tensors copied into ``info``, one per `metric_names` at least.
        """

    @abc.abstractmethod
    def _reset_where(self, mask: torch.Tensor) -> None:
        """Reset the task state of the copies where ``mask`` is true."""

    @abc.abstractmethod
    def _observe(self) -> torch.Tensor:
        """Return the observation of every copy from the current state."""

    def _episode_extras(self, episode: dict[str, torch.Tensor]) -> None:  # noqa: B027
        """Add derived per-episode metrics to ``episode`` (in place; default: none)."""

    def _prompt_extras(self, ids: torch.Tensor) -> list[dict[str, Any]]:
        """Return, per selected copy, prompt variables that the observation lacks."""
        return [{} for _ in range(len(ids))]

    def _draw(self) -> torch.Tensor:
        """Draw one 64-bit number (int64 ``[num_envs]``) per copy and advance every counter."""
        assert self._keys is not None
        values = rng.draw(self._keys, self._ctr)
        self._ctr = self._ctr + 1
        return values

    def _draw_many(self, ids: torch.Tensor, count: int) -> torch.Tensor:
        """Draw ``count`` numbers for each copy in ``ids`` (int64 ``[len(ids), count]``)."""
        assert self._keys is not None
        values = rng.draws(self._keys[ids], self._ctr[ids], count)
        self._ctr[ids] += count
        return values

    def _check_actions(self, actions: object) -> torch.Tensor:
        if not isinstance(actions, torch.Tensor):
            raise ValueError(
                f"actions: expected a torch integer tensor of shape ({self.num_envs},), "
                f"got {type(actions).__name__}"
            )
        if actions.shape != (self.num_envs,):
            raise ValueError(
                f"actions: expected shape ({self.num_envs},), got {tuple(actions.shape)}"
            )
        dtype = actions.dtype
        if dtype.is_floating_point or dtype.is_complex or dtype == torch.bool:
            raise ValueError(f"actions: expected an integer tensor, got dtype {dtype}")
        actions = actions.to(device=self.device, dtype=torch.int64)
        low, high = torch.aminmax(actions)
        if int(low) < 0 or int(high) >= self.num_actions:
            bad = actions[(actions < 0) | (actions >= self.num_actions)][0].item()
            raise ValueError(
                f"actions: every action must be in 0..{self.num_actions - 1} "
                f"({', '.join(self.action_names)}), got {bad}"
            )
        return actions

    def _env_id(self, env_id: object) -> int:
        return check_int(env_id, "env_id", 0, self.num_envs - 1)

    def _env_ids(self, env_ids: object) -> torch.Tensor:
        if env_ids is None:
            return torch.arange(self.num_envs, device=self.device)
        if isinstance(env_ids, numbers.Integral) and not isinstance(env_ids, bool):
            return torch.tensor([self._env_id(env_ids)], device=self.device)
        ids = torch.as_tensor(env_ids, device=self.device).reshape(-1).to(torch.int64)
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= self.num_envs):
            raise ValueError(f"env_ids: expected indices in 0..{self.num_envs - 1}")
        return ids

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_envs={self.num_envs}, device={str(self.device)!r}, "
            f"shaping_coef={self.shaping_coef}, max_steps={self.max_steps})"
        )
