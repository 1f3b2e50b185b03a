"""The deliberation MDP, batched: N task copies, a panel, and the actor's reward, defined once.

The learner and `DeliberationEnv` both step it; the KL anchor is the learner's (docs/learning.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import torch

from amuled_ma.errors import AmuledError

if TYPE_CHECKING:
    from amuled_ma.tasks.base import BatchedTask

#: ``(observations [N, obs_dim], task) -> fused beliefs [N, A]``: a learner's feedback
#: (`Feedback`) or any callable of that shape.
FeedbackFn = Callable[[torch.Tensor, Any], Any]


def actor_reward(
    r_task: torch.Tensor,
    fused_taken: torch.Tensor | None,
    *,
    task_weight: float,
    feedback_coef: float,
) -> torch.Tensor:
    """The actor's reward: ``task_weight * r_task + feedback_coef * fused[a]``.

    ``fused_taken`` None (base training) gives ``task_weight * r_task``. Returns ``[N]`` in the
    inputs' dtype.
    """
    if fused_taken is None:
        return task_weight * r_task
    return task_weight * r_task + feedback_coef * fused_taken


def as_tensor(
    value: npt.ArrayLike | torch.Tensor, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """Return ``value`` as a ``dtype`` tensor on ``device`` (itself when it already is one)."""
    if isinstance(value, torch.Tensor) and value.dtype == dtype and value.device == device:
        return value
    return torch.as_tensor(value, device=device).to(dtype)


@dataclass
class DeliberationStep:
    """What one batched step returns (``[N]`` per copy; ``obs`` after the task's automatic reset).

    ``fused`` ``[N, A]`` are the beliefs of the states acted in and ``feedback`` = ``fused[a]``;
    both None without feedback.
    """

    obs: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    info: dict[str, Any]
    r_task: torch.Tensor
    fused: torch.Tensor | None
    feedback: torch.Tensor | None


class BatchedDeliberation:
    """``N`` copies of a task, the feedback that answers for them, and the actor's reward.

    Call `reset` before the first `step`. ``feedback`` None: base training, or the caller
    passes the fused beliefs to `step`.
    """

    def __init__(
        self,
        task: BatchedTask,
        feedback: FeedbackFn | None = None,
        *,
        task_weight: float = 1.0,
        feedback_coef: float = 1.0,
    ) -> None:
        self.task = task
        self.feedback = feedback
        self.task_weight = float(task_weight)
        self.feedback_coef = float(feedback_coef)
        self.num_envs = int(task.num_envs)
        self.num_actions = int(task.num_actions)
        self.device = torch.device(getattr(task, "device", "cpu"))
        #: The current observations ``[N, obs_dim]``; set by `reset`.
        self.obs = torch.zeros(self.num_envs, int(task.obs_dim), device=self.device)

    def _as(self, value: npt.ArrayLike | torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        return as_tensor(value, dtype, self.device)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every copy (seeding the task when ``seed`` is given); return observations."""
        obs = self.task.reset() if seed is None else self.task.reset(seed=seed)
        self.obs = self._as(obs, torch.float32)
        return self.obs

    def step(
        self, actions: torch.Tensor, fused: npt.ArrayLike | torch.Tensor | None = None
    ) -> DeliberationStep:
        """Read the fused beliefs (``fused``, else asked), step the task, reward."""
        if fused is None and self.feedback is not None:
            fused = self._as(self.feedback(self.obs, self.task), torch.float32)
        elif fused is not None and not isinstance(fused, torch.Tensor):
            fused = torch.as_tensor(np.asarray(fused), device=self.device)
        taken = None
        if fused is not None:
            taken = fused.gather(1, actions.reshape(-1, 1).to(fused.device)).squeeze(1)
        obs, r_task, terminated, truncated, info = self.task.step(actions)
        self.obs = self._as(obs, torch.float32)
        r_task = self._as(r_task, torch.float32 if taken is None else taken.dtype)
        reward = actor_reward(
            r_task, taken, task_weight=self.task_weight, feedback_coef=self.feedback_coef
        )
        return DeliberationStep(
            obs=self.obs,
            reward=reward,
            terminated=self._as(terminated, torch.bool),
            truncated=self._as(truncated, torch.bool),
            info=info,
            r_task=r_task,
            fused=fused,
            feedback=taken,
        )


class CopiesView:
    """Copies ``start .. start + count - 1`` of a batched task, seen as a task of ``count``.

    A population member's feedback sees its copies numbered from 0, as in a lone run; every
    other attribute is the task's.
    """

    _LOCAL_IDS = ("prompt_variables", "state_prompts")

    def __init__(self, task: BatchedTask, start: int, count: int, variables: Any = None) -> None:
        self.task = task
        self.start = int(start)
        self.num_envs = int(count)
        self.variables = variables

    def __getattr__(self, name: str) -> Any:
        value = getattr(self.task, name)
        if name == "obs":
            return value[self.start : self.start + self.num_envs]
        if name in self._LOCAL_IDS and callable(value):
            if name == "prompt_variables" and self.variables is not None:
                value = self.variables

            def local(env_ids: int | Sequence[int] | None = None) -> Any:
                """``value`` of the population's copies of local ``env_ids`` (None: this view's)."""
                if env_ids is None:
                    return value(list(range(self.start, self.start + self.num_envs)))
                if isinstance(env_ids, int | np.integer):
                    return value([self.start + int(env_ids)])
                return value([self.start + int(i) for i in env_ids])

            return local
        return value


class MemberFeedback:
    """A population's feedback: member ``p``'s feedback answers for its ``E`` copies.

    Prompt variables are read for every copy once per step. A member whose feedback fails
    (an `AmuledError`, a non-finite belief) is not asked again: the reason is kept in
    `failures` and its rows get zeros; the other members run exactly as they would have.
    """

    def __init__(self, feedbacks: Sequence[FeedbackFn], copies: int) -> None:
        self.feedbacks = list(feedbacks)
        self.copies = int(copies)
        self._views: list[CopiesView] = []
        self._task: Any = None
        self._variables: list[Any] | None = None
        #: member -> why its feedback failed (the trainer stops it after the iteration)
        self.failures: dict[int, str] = {}

    def prompt_variables(self, env_ids: Sequence[int]) -> list[dict[str, Any]]:
        """The prompt variables of copies ``env_ids`` now (every copy read once a step)."""
        if self._variables is None:
            self._variables = list(self._task.prompt_variables())
        return [self._variables[i] for i in env_ids]

    def __call__(self, obs: torch.Tensor, task: BatchedTask) -> np.ndarray:
        """The fused beliefs ``[P x E, A]`` of every copy, each from its member's feedback."""
        if not self._views or self._task is not task:  # each member's view, once per task
            self._task = task
            variables = self.prompt_variables if hasattr(task, "prompt_variables") else None
            self._views = [
                CopiesView(task, p * self.copies, self.copies, variables)
                for p in range(len(self.feedbacks))
            ]
        self._variables = None  # the states changed since the last step
        blocks = obs.split(self.copies)
        parts: list[np.ndarray] = []
        for member, (feedback, view, rows) in enumerate(
            zip(self.feedbacks, self._views, blocks, strict=True)
        ):
            part = None
            if member not in self.failures:
                try:
                    part = np.asarray(feedback(rows, view))
                except AmuledError as error:  # its source stayed down, a replay miss, ...
                    self.failures[member] = str(error)
                if part is not None and not np.isfinite(part).all():
                    self.failures[member] = (
                        "its feedback gave a belief that is not a finite number (NaN or inf)"
                    )
            if member in self.failures or part is None:  # a stand-in, never learnt from
                part = np.zeros((len(rows), task.num_actions))
            parts.append(part)
        self._variables = None
        return np.concatenate(parts)
