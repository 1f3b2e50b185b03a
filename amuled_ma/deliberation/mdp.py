"""The deliberation MDP, batched: N task copies, a panel, and the actor's reward, defined once.

Both views of a deliberation step run through `BatchedDeliberation`:

- the learner (`DeliberationVecEnv`, rsl-rl's ``VecEnv``)
  trains in it with ``N`` copies; its feedback (a moral panel over a belief source, a
  replay, a demonstrator, ...) answers for all ``N`` states in one call;
- the PettingZoo `DeliberationEnv` is the same MDP with
  one copy, where the cluster agents' actions are the beliefs and its arbiter fuses them.

Each step, the fused belief of the state the action is taken in is read *before* the task
steps, then the task steps, then `actor_reward` turns the task reward and the fused
belief of the taken action into the actor's reward. The KL anchor to the base policy is
not part of the MDP: it needs the policies, so the learner adds it
(`AnchoredPPO`).
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

    The one definition used by training and by the PettingZoo view. ``r_task`` is the
    task's reward, ``r_env + shaping_coef * r_shaping`` (the task computes that sum), and
    ``fused[a]`` the fused belief of the action taken in the state it was taken in. Base
    training has no feedback (``fused_taken`` is None) and is rewarded ``task_weight *
    r_task``.

    Args:
        r_task: Task reward per copy ``[N]``.
        fused_taken: Fused belief of each copy's action ``[N]``, or None (no feedback).
        task_weight: Weight of the task reward (``[finetune] env_reward_coef`` when
            fine-tuning, 1 in base training, ``r_env_weight`` in the PettingZoo env).
        feedback_coef: Weight ``c`` of the feedback term.

    Returns:
        The reward ``[N]``, in the dtype of the inputs.

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
    """What one batched step returns.

    Attributes:
        obs: Next observations ``[N, obs_dim]`` (after the task's automatic reset).
        reward: The actor's reward ``[N]`` (`actor_reward`).
        terminated: ``[N]`` bool.
        truncated: ``[N]`` bool.
        info: The task's info (``r_env``, ``r_shaping``, ``final_obs``, ``episode``, ...).
        r_task: The task reward ``[N]``.
        fused: The fused beliefs of the states the actions were taken in ``[N, A]``, or
            None without feedback.
        feedback: ``fused[a]`` per copy ``[N]``, or None without feedback.

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

    Call `reset` before the first `step`.

    Args:
        task: A batched task (`tasks`), any number of copies.
        feedback: Answers the fused beliefs of all copies' states in one call; None for base
            training or when the caller passes the fused beliefs to `step` itself.
        task_weight: Weight of the task reward in the actor's reward.
        feedback_coef: Weight of the fused belief of the action taken.

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

    def beliefs(self) -> torch.Tensor | None:
        """The feedback's fused beliefs ``[N, A]`` for the current states (None without)."""
        if self.feedback is None:
            return None
        return self._as(self.feedback(self.obs, self.task), torch.float32)

    def step(
        self, actions: torch.Tensor, fused: npt.ArrayLike | torch.Tensor | None = None
    ) -> DeliberationStep:
        """Read the fused beliefs of the current states, step the task, reward the actor.

        Args:
            actions: Action index per copy ``[N]`` (long).
            fused: The fused beliefs ``[N, A]`` of the current states, when the caller has
                them (the PettingZoo view fuses its cluster agents' actions); None asks
                `feedback` (or gives no feedback term when there is none).

        Returns:
            The step (`DeliberationStep`).

        """
        if fused is None:
            fused = self.beliefs()
        elif not isinstance(fused, torch.Tensor):
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

    What a population member's feedback is handed (`MemberFeedback`): its copies
    numbered from 0, as in a lone run, so ``prompt_variables(ids)`` (and
    ``state_prompts``) reads copy ``start + id`` of the population's task and ``obs`` is
    the member's rows. Every other attribute is the task's.

    Args:
        task: The population's batched task.
        start: First copy.
        count: Number of copies.
        variables: Reads the prompt variables of copies by their indices in ``task``
            (default: ``task.prompt_variables``); `MemberFeedback` hands its
            once-per-step reading of every copy.

    """

    _LOCAL_IDS = ("prompt_variables", "state_prompts")

    def __init__(self, task: BatchedTask, start: int, count: int, variables: Any = None) -> None:
        self.task = task
        self.start = int(start)
        self.num_envs = int(count)
        self.variables = variables

    def global_ids(self, env_ids: int | Sequence[int] | None = None) -> list[int]:
        """The population's copy indices of local ``env_ids`` (None: all of this view)."""
        if env_ids is None:
            return list(range(self.start, self.start + self.num_envs))
        if isinstance(env_ids, int | np.integer):
            return [self.start + int(env_ids)]
        return [self.start + int(i) for i in env_ids]

    def __getattr__(self, name: str) -> Any:
        value = getattr(self.task, name)
        if name == "obs":
            return value[self.start : self.start + self.num_envs]
        if name in self._LOCAL_IDS and callable(value):
            if name == "prompt_variables" and self.variables is not None:
                value = self.variables

            def local(env_ids: Any = None) -> Any:
                return value(self.global_ids(env_ids))

            return local
        return value


class MemberFeedback:
    """A population's feedback: member ``p``'s feedback answers for member ``p``'s copies.

    A population of ``P`` members trains in one task of ``P x E`` copies, member ``p``
    owning copies ``p*E .. p*E + E - 1``; each member's feedback (its own panel, fusion
    rule, memo) is called on its rows with its copies as a task of ``E``
    (`CopiesView`), exactly as in a lone run, and the answers are stacked. The
    prompt variables of the states (read by a feedback keyed by prompt) are read for
    every copy at once, on the first request of a step, and served to each member.

    A member whose feedback fails (an `AmuledError`, a belief
    that is not finite) is not asked again: the reason is kept in `failures`, its
    rows get zeros that nothing learns from (the population trainer stops the member after
    the iteration and keeps its last checkpoint), and the other members' iteration runs
    exactly as it would have.

    Args:
        feedbacks: One feedback per member (`FeedbackFn`).
        copies: Copies per member ``E``.

    """

    def __init__(self, feedbacks: Sequence[FeedbackFn], copies: int) -> None:
        self.feedbacks = list(feedbacks)
        self.copies = int(copies)
        self._views: list[CopiesView] = []
        self._task: Any = None
        self._variables: list[Any] | None = None
        #: member -> why its feedback failed (the trainer stops it after the iteration)
        self.failures: dict[int, str] = {}

    def views(self, task: BatchedTask) -> list[CopiesView]:
        """Each member's `CopiesView` of ``task`` (made once per task)."""
        if not self._views or self._task is not task:
            self._task = task
            variables = self.prompt_variables if hasattr(task, "prompt_variables") else None
            self._views = [
                CopiesView(task, p * self.copies, self.copies, variables)
                for p in range(len(self.feedbacks))
            ]
        return self._views

    def prompt_variables(self, env_ids: Sequence[int]) -> list[dict[str, Any]]:
        """The prompt variables of copies ``env_ids`` now (every copy read once a step)."""
        if self._variables is None:
            self._variables = list(self._task.prompt_variables())
        return [self._variables[i] for i in env_ids]

    def __call__(self, obs: torch.Tensor, task: BatchedTask) -> np.ndarray:
        """The fused beliefs ``[P x E, A]`` of every copy, each from its member's feedback."""
        views = self.views(task)
        self._variables = None  # the states changed since the last step
        blocks = obs.split(self.copies)
        parts: list[np.ndarray] = []
        for member, (feedback, view, rows) in enumerate(
            zip(self.feedbacks, views, blocks, strict=True)
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
