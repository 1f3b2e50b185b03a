"""One rollout of evaluation episodes: the loop the evaluator and the episode trace share.

Evaluation episode ``K`` is what copy ``K`` of one ``N``-copy task plays (seed ``seed + K``).
A sampled draw is one multinomial over the ``[N, A]`` batch from one generator, so it depends
on ``N``: episode ``K`` is replayed by the same ``N``-copy rollout, never by one copy alone.
A finished copy resets and keeps stepping until the copies asked for end their first episode.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from amuled_ma.errors import ScenarioError
from amuled_ma.evaluate.results import MODES
from amuled_ma.learn.policies import action_log_probs
from amuled_ma.tasks import make_task

if TYPE_CHECKING:
    from amuled_ma.scenario import TaskConfig
    from amuled_ma.tasks.base import BatchedTask

#: Keys of ``info["episode"]`` that are book-keeping, not metrics.
SKIP = {"done", "return"}


class Observer:
    """Watches a rollout's steps; every method does nothing unless overridden."""

    def start(self, task: BatchedTask, obs: torch.Tensor) -> None:
        """Called once after the reset, with the first observations ``[N, obs_dim]``."""

    def before_step(
        self, task: BatchedTask, obs: torch.Tensor, logp: torch.Tensor, actions: torch.Tensor
    ) -> None:
        """Called before each step with the states, the policy's ``log pi`` and the actions."""

    def after_step(
        self,
        task: BatchedTask,
        obs: torch.Tensor,
        terminated: torch.Tensor,
        truncated: torch.Tensor,
        info: Mapping[str, Any],
    ) -> None:
        """Called after each step with what the task returned (``obs`` after auto-reset)."""


def _to_float(value: float | torch.Tensor | np.generic) -> float:
    return float(value.item() if hasattr(value, "item") else value)


def step_events(
    info: Mapping[str, Any], copy: int, copies: int, skip: Collection[str] = ()
) -> Iterator[tuple[str, float]]:
    """``(key, value)`` of copy ``copy`` for each 1-D ``copies``-tensor of a step's ``info``."""
    for key, value in info.items():
        if key in ("final_obs", "episode") or key in skip or not torch.is_tensor(value):
            continue
        if value.dim() == 1 and value.numel() == copies:
            yield key, _to_float(value[copy])


def episode_metrics(
    episode: Mapping[str, Any], copy: int, copies: int, skip: Collection[str] = SKIP
) -> dict[str, float]:
    """Copy ``copy``'s value of each ``copies``-element entry of ``info["episode"]`` not skipped."""
    out = {}
    for key, value in episode.items():
        tensor = torch.as_tensor(value)
        if key not in skip and tensor.dim() >= 1 and tensor.numel() == copies:
            out[key] = _to_float(tensor.reshape(-1)[copy])
    return out


def rollout(
    actor: torch.nn.Module,
    task_config: TaskConfig,
    *,
    episodes: int,
    mode: str = "greedy",
    seed: int,
    task_factory: Callable[..., Any] | None = None,
    observers: Sequence[Observer] = (),
    until: Sequence[int] | None = None,
) -> list[dict[str, float] | None]:
    """Per copy of ``episodes`` (copy ``i`` seeded ``seed + i``), its first episode's metrics.

    A copy's metrics are its ``info["episode"]`` entries and ``terminated``, None for a copy still
    playing when the copies of ``until`` (default: all) have ended. ``seed`` also seeds the action
    draws; torch runs single-threaded from here on, as the trainer. ScenarioError: unknown
    ``mode``, or a copy in ``until`` outside ``0..N-1``.
    """
    if mode not in MODES:
        raise ScenarioError(f"mode: expected one of {', '.join(MODES)}, found {mode!r}")
    wanted = list(range(episodes)) if until is None else [int(i) for i in until]
    if any(not 0 <= i < episodes for i in wanted):
        raise ScenarioError(f"until: expected copies in 0..{episodes - 1}, found {wanted}")
    # small nets on CPU: a second thread only contends (a 50-row pass: 11.5 ms on 2, 0.36 ms on 1)
    torch.set_num_threads(1)
    task = (task_factory or make_task)(task_config, episodes, shaping_coef=0.0, seed=seed)
    obs = torch.as_tensor(task.reset()).float()
    gen = torch.Generator().manual_seed(seed)
    done_once = torch.zeros(episodes, dtype=torch.bool)
    watched = None if until is None else torch.as_tensor(wanted, dtype=torch.long)
    records: list[dict[str, float] | None] = [None] * episodes
    for observer in observers:
        observer.start(task, obs)
    limit = int(getattr(task, "max_steps", 1000)) + 1
    with torch.inference_mode():
        for _ in range(limit):
            logp = action_log_probs(actor, obs)
            if mode == "greedy":
                actions = logp.argmax(dim=-1)
            else:
                actions = torch.multinomial(logp.exp(), 1, generator=gen).squeeze(-1)
            for observer in observers:
                observer.before_step(task, obs, logp, actions)
            obs, _, terminated, truncated, info = task.step(actions)
            obs = torch.as_tensor(obs).float()
            terminated, truncated = torch.as_tensor(terminated), torch.as_tensor(truncated)
            for observer in observers:
                observer.after_step(task, obs, terminated, truncated, info)
            new = (terminated | truncated) & ~done_once
            if bool(new.any()):
                episode = info.get("episode", {})
                for i in new.nonzero().squeeze(-1).tolist():
                    metrics = episode_metrics(episode, i, episodes)
                    records[i] = {**metrics, "terminated": float(bool(terminated[i]))}
                done_once |= new
            if bool((done_once if watched is None else done_once[watched]).all()):
                break
    return records


class TrajectoryRecorder(Observer):
    """The first episode of one copy for pictures: observations, actions, events, layout.

    ``trajectory``'s last observation is the episode's final one (before the copy's reset).
    """

    def __init__(self, copy: int = 0) -> None:
        self.copy = copy
        self.trajectory: dict[str, Any] = {"obs": [], "actions": [], "events": {}}
        self.done = False
        self._actions: torch.Tensor | None = None

    def start(self, task: BatchedTask, obs: torch.Tensor) -> None:
        """Record the first observation (and FindMilk's babies)."""
        self.trajectory["obs"].append(obs[self.copy].tolist())
        if hasattr(task, "baby_positions"):
            self.trajectory["layout"] = task.baby_positions(self.copy)

    def before_step(
        self, task: BatchedTask, obs: torch.Tensor, logp: torch.Tensor, actions: torch.Tensor
    ) -> None:
        """Keep the actions until the step is done."""
        self._actions = actions

    def after_step(
        self,
        task: BatchedTask,
        obs: torch.Tensor,
        terminated: torch.Tensor,
        truncated: torch.Tensor,
        info: Mapping[str, Any],
    ) -> None:
        """Record the step of the copy, until its first episode has ended."""
        if self.done:
            return
        k, n = self.copy, len(obs)
        assert self._actions is not None
        self.trajectory["actions"].append(int(self._actions[k]))
        final = info.get("final_obs", obs)
        self.trajectory["obs"].append(torch.as_tensor(final)[k].tolist())
        events = self.trajectory["events"]
        for key, value in step_events(info, k, n):
            events.setdefault(key, []).append(value)
        self.done = bool(terminated[k]) or bool(truncated[k])
