"""One evaluation episode, step by step: what the policy saw, did and would have done.

Episode ``K`` is replayed with the evaluator's own rollout (same ``N`` copies, seeds and
action draws), so it is the episode ``amuled evaluate`` scored, in greedy and sampled mode.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from amuled_ma.deliberation.state_key import freeze
from amuled_ma.errors import CheckpointError, ScenarioError
from amuled_ma.evaluate.rollout import TrajectoryRecorder, episode_metrics, rollout
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.records.variants import Variant
from amuled_ma.tasks.driving import Driving
from amuled_ma.tasks.findmilk import FindMilk

if TYPE_CHECKING:
    from rsl_rl.models import MLPModel

    from amuled_ma.deliberation.feedback_base import Feedback
    from amuled_ma.scenario import EvaluationConfig, PPOConfig, Scenario, TaskConfig
    from amuled_ma.tasks.base import BatchedTask


@dataclass(frozen=True)
class TrainedVariant:
    """A trained variant as the viewer and ``amuled explain`` need it (resolved by the caller)."""

    name: str
    checkpoint: Path
    scenario: Scenario
    variant: Variant | None
    base_checkpoint: Path | None = None

    @property
    def feedback(self) -> str | None:
        """The feedback of a fine-tune (``amuled``, ``human:rules``, ...), None otherwise."""
        return self.variant.feedback if self.variant and self.variant.finetuning else None


@dataclass
class Episode:
    """One evaluation episode of one policy (copy ``K`` of ``episodes``), step by step.

    ``T`` steps; state ``t`` is the state step ``t`` was taken in (state ``T`` the last one
    reached). ``obs`` and ``frames`` hold ``T + 1`` states, ``prompt_vars``, ``actions``,
    ``probs`` ``[T, A]``, ``events`` and ``rewards`` (``r_env``) ``T`` steps; ``base_*`` are the
    base policy's (None without one), ``live_*`` a non-panel feedback's (None otherwise);
    ``seed`` is ``[evaluation].seed + K``; ``terminated`` means ended by the task, not the limit.
    """

    task: str
    episode: int
    seed: int
    mode: str
    action_names: tuple[str, ...]
    obs: np.ndarray
    prompt_vars: list[dict[str, Any]]
    actions: np.ndarray
    probs: np.ndarray
    base_actions: np.ndarray | None
    base_probs: np.ndarray | None
    events: dict[str, np.ndarray]
    rewards: np.ndarray
    frames: list[Any]
    layout: dict[str, Any] | None
    terminated: bool
    metrics: dict[str, float]
    live_beliefs: np.ndarray | None = None
    live_statuses: list[tuple[tuple[str, str], ...]] | None = None
    episodes: int = 1

    @property
    def length(self) -> int:
        """Number of steps ``T``."""
        return len(self.actions)

    def unique_states(self) -> tuple[list[int], np.ndarray]:
        """``(first, index)``: each distinct state's first step, and each step's position in it."""
        first: list[int] = []
        seen: dict[bytes, int] = {}
        index = np.empty(self.length, dtype=np.int64)
        rows = np.ascontiguousarray(self.obs[: self.length], dtype=np.float64)
        for t in range(self.length):
            key = rows[t].tobytes() + freeze(self.prompt_vars[t])
            u = seen.get(key)
            if u is None:
                u = seen[key] = len(first)
                first.append(t)
            index[t] = u
        return first, index


def frame_of(task: BatchedTask, copy: int = 0) -> Any:
    """A small, JSON-ready picture of one task copy (FindMilk: the robot's ``[x, y]``)."""
    if isinstance(task, FindMilk):
        x, y = (int(v) for v in task.position[copy].tolist())
        return [x, y]
    if isinstance(task, Driving):
        objects = task.objects(copy)
        return [int(task.lane[copy]), objects["car"], objects["grandma"]]
    return task.render_ansi(copy)


def layout_of(task: BatchedTask, obs: torch.Tensor, copy: int = 0) -> dict[str, Any] | None:
    """What stays fixed over an episode of one copy (FindMilk: the milk and the babies)."""
    if isinstance(task, FindMilk):
        babies = task.baby_positions(copy)
        milk = [int(v) for v in obs[copy, 2:4].tolist()]
        return {
            "size": int(task.grid_size),
            "milk": milk,
            "crying": [list(p) for p in babies["crying"]],
            "sleeping": [list(p) for p in babies["sleeping"]],
        }
    if isinstance(task, Driving):
        return {"lanes": int(task.num_lanes), "distance": 8}
    return None


class _Tracer(TrajectoryRecorder):
    """Records copy ``K`` of a rollout step by step, until its first episode ends."""

    def __init__(self, copy: int, base_actor: MLPModel, live_feedback: Feedback | None) -> None:
        super().__init__(copy)
        self.base_actor = base_actor
        self.live_feedback = live_feedback
        self.layout: dict[str, Any] | None = None
        self.frames: list[Any] = []
        self.prompt_vars: list[dict[str, Any]] = []
        self.probs: list[np.ndarray] = []
        self.base_actions: list[int] = []
        self.base_probs: list[np.ndarray] = []
        self.live: list[np.ndarray] = []
        self.live_statuses: list[tuple[tuple[str, str], ...]] = []
        self.metrics: dict[str, float] = {}
        self.terminated = False
        self.task_name = ""
        self.action_names: tuple[str, ...] = ()

    def start(self, task: BatchedTask, obs: torch.Tensor) -> None:
        super().start(task, obs)
        self.task_name, self.action_names = str(task.name), tuple(task.action_names)
        self.layout = layout_of(task, obs, self.copy)
        self.frames.append(frame_of(task, self.copy))

    def before_step(
        self, task: BatchedTask, obs: torch.Tensor, logp: torch.Tensor, actions: torch.Tensor
    ) -> None:
        super().before_step(task, obs, logp, actions)
        if self.done:
            return
        k = self.copy
        row = obs[k : k + 1]
        self.prompt_vars.append(dict(task.prompt_variables([k])[0]))
        feedback = self.live_feedback
        if feedback is not None:
            before = Counter(feedback.agent_statuses)
            self.live.append(np.asarray(feedback(row, task, [k])[0], dtype=np.float64))
            after = Counter(feedback.agent_statuses)
            self.live_statuses.append(tuple((after - before).keys()))
        self.probs.append(logp[k].exp().numpy().copy())
        if self.base_actor is not None:
            base_logp = action_log_probs(self.base_actor, row)
            self.base_probs.append(base_logp[0].exp().numpy().copy())
            self.base_actions.append(int(base_logp[0].argmax()))

    def after_step(
        self,
        task: BatchedTask,
        obs: torch.Tensor,
        terminated: torch.Tensor,
        truncated: torch.Tensor,
        info: Mapping[str, Any],
    ) -> None:
        if self.done:
            return
        super().after_step(task, obs, terminated, truncated, info)
        k = self.copy
        if not self.done:
            self.frames.append(frame_of(task, k))
            return
        self.terminated = bool(terminated[k])
        self.metrics = episode_metrics(info.get("episode") or {}, k, len(obs), skip=("done",))
        # the task has reset the copy: the last picture is drawn from the final obs
        final = torch.as_tensor(info.get("final_obs", obs)).float()[k]
        previous = self.frames[-1]
        if task.name == "findmilk":
            previous = [int(final[0]), int(final[1])]
        elif task.name == "driving":
            cars = [[ln, d - 1] for ln, d in previous[1] if d - 1 > 0]
            grandmas = [[ln, d - 3] for ln, d in previous[2] if d - 3 > 0]
            previous = [int(torch.argmax(final[6:])), cars, grandmas]
        self.frames.append(previous)


def replay_episode(
    actor: torch.nn.Module,
    task_config: TaskConfig,
    evaluation: EvaluationConfig,
    *,
    episode: int = 0,
    mode: str = "greedy",
    episodes: int | None = None,
    base_actor: torch.nn.Module | None = None,
    live_feedback: Feedback | None = None,
    task_factory: Callable[..., Any] | None = None,
) -> Episode:
    """Play evaluation episode ``K = episode`` of ``episodes`` (default ``[evaluation].episodes``).

    ``base_actor`` is asked in the same states; ``live_feedback`` (one that needs the live task:
    human, fused-only replay) about every state. ScenarioError: bad ``mode`` or ``episode``.
    """
    n = int(evaluation.episodes if episodes is None else episodes)
    if not 0 <= episode < n:
        raise ScenarioError(
            f"episode: expected an evaluation episode 0..{n - 1} (the evaluation plays {n} "
            f"episodes, [evaluation].episodes or --episodes), found {episode}"
        )
    seed = int(evaluation.seed)
    tracer = _Tracer(int(episode), base_actor, live_feedback)
    rollout(
        actor,
        task_config,
        episodes=n,
        mode=mode,
        seed=seed,
        task_factory=task_factory,
        observers=(tracer,),
        until=(int(episode),),
    )
    num_actions = len(tracer.action_names)
    events = {k: np.asarray(v) for k, v in tracer.trajectory["events"].items()}
    rewards = events.pop("r_env")
    events.pop("r_shaping", None)
    return Episode(
        task=tracer.task_name,
        episode=int(episode),
        seed=seed + int(episode),
        mode=mode,
        action_names=tracer.action_names,
        obs=np.asarray(tracer.trajectory["obs"], dtype=np.float32),
        prompt_vars=tracer.prompt_vars,
        actions=np.asarray(tracer.trajectory["actions"], dtype=np.int64),
        probs=np.stack(tracer.probs) if tracer.probs else np.empty((0, num_actions)),
        base_actions=np.asarray(tracer.base_actions, dtype=np.int64) if base_actor else None,
        base_probs=np.stack(tracer.base_probs) if base_actor is not None and tracer.probs else None,
        events=events,
        rewards=rewards,
        frames=tracer.frames,
        layout=tracer.layout,
        terminated=tracer.terminated,
        metrics=tracer.metrics,
        live_beliefs=np.stack(tracer.live) if tracer.live else None,
        live_statuses=tracer.live_statuses if live_feedback is not None else None,
        episodes=n,
    )


def load_actor(checkpoint: Path, ppo: PPOConfig) -> torch.nn.Module:
    """The actor in eval mode (`load_policy`); CheckpointError: missing, or not of ``ppo``'s net."""
    if not Path(checkpoint).is_file():
        raise CheckpointError(
            f"no policy at {checkpoint}; train the variant first ('amuled run' or "
            "'amuled finetune') or name another with --variant"
        )
    return load_policy(Path(checkpoint), ppo)


def replay_variant(
    trained: TrainedVariant,
    *,
    episode: int = 0,
    mode: str = "greedy",
    episodes: int | None = None,
    live_feedback: Feedback | None = None,
) -> Episode:
    """Replay an evaluation episode of a trained variant, its base policy beside it."""
    scenario = trained.scenario
    actor = load_actor(trained.checkpoint, scenario.ppo)
    base = trained.base_checkpoint
    base_actor = load_actor(base, scenario.ppo) if base is not None else None
    return replay_episode(
        actor,
        scenario.task,
        scenario.evaluation,
        episode=episode,
        mode=mode,
        episodes=episodes,
        base_actor=base_actor,
        live_feedback=live_feedback,
    )
