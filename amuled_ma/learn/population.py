"""Population training: P jobs of one shape trained together, each as it trains alone.

A fine-tune with the authors' recipe (1 copy x 128 steps x 1,000 iterations, 8 epochs of
4 mini-batches) is made of tiny tensors: its cost is Python and kernel launches, not
arithmetic. :class:`PopulationTrainer` trains ``P`` such jobs (:class:`~amuled_ma.learn.
population_groups.MemberSpec`, what :class:`~amuled_ma.learn.trainer.Trainer` takes) in
one process, through rsl-rl's own runner (``runner.learn(1)`` per iteration):

- one batched task of ``P x E`` copies (member ``p`` owns copies ``p*E .. p*E + E - 1``),
  in one deliberation MDP whose feedback asks each member's own feedback about its
  copies (:class:`~amuled_ma.deliberation.mdp.MemberFeedback`; the belief store behind
  them may be one);
- one stacked actor, critic and base actor (:mod:`amuled_ma.learn.population_models`),
  plugged into rsl-rl by ``class_name``, and :class:`~amuled_ma.learn.population_ppo.
  PopulationPPO`, which keeps each member's update its own (mini-batches, advantage
  normalisation, gradient clipping, loss scale) and each member's random stream its own.

Each member **starts where its lone run starts**: its lone ``Trainer`` is built (its seed,
its base policy or its checkpoint when resumed) and its weights, Adam state, torch random
state and task copies are taken from it. Each member **ends as a lone job ends**: its
``model_last.pt`` (same format: resume, evaluation, the report and the viewer read it as a
lone job's), ``curve.json``, ``train_cfg.json`` (its lone config), ``feedback.json`` and
TensorBoard events, in its own folder. ``tests/learn/test_population.py`` trains members
together and alone from the same seeds and compares losses, parameters and curves.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

from rsl_rl.runners import OnPolicyRunner

from amuled_ma.deliberation.mdp import BatchedDeliberation, MemberFeedback
from amuled_ma.errors import AmuledError, Terminated
from amuled_ma.learn.checkpoints import LAST, CheckpointWriteError, write_checkpoint
from amuled_ma.learn.population_groups import (
    MEMBER_ALGORITHM_KEYS,
    MemberSpec,
    population_key,
    shared_config,
)
from amuled_ma.learn.population_models import member_state, stack_states
from amuled_ma.learn.population_ppo import PopulationPPO
from amuled_ma.learn.population_state import (
    member_env_state,
    member_optimizer_state,
    split_episodes,
    stack_env_states,
    stack_optimizer_states,
)
from amuled_ma.learn.trainer import Trainer, TrainOutcome
from amuled_ma.learn.vecenv import DeliberationVecEnv
from amuled_ma.tasks import make_task

__all__ = [
    "POPULATION_MODEL",
    "POPULATION_PPO",
    "MemberStart",
    "PopulationMember",
    "PopulationTrainer",
    "population_config",
    "train_population",
]

#: ``module:Class`` names rsl-rl resolves for a population.
POPULATION_MODEL = "amuled_ma.learn.population_models:PopulationMLPModel"
POPULATION_CATEGORICAL = "amuled_ma.learn.population_models:PopulationCategoricalDistribution"
POPULATION_PPO = "amuled_ma.learn.population_ppo:PopulationPPO"


def _quiet(fn: Callable[[], Any]) -> Any:
    with contextlib.redirect_stdout(io.StringIO()):
        return fn()


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


@dataclass
class MemberStart:
    """Where a member starts: its lone :class:`Trainer`'s state after construction.

    Attributes:
        cfg: Its lone rsl-rl config (``train_cfg.json``).
        actor: Actor state dict.
        critic: Critic state dict.
        optimizer: Adam's state dict.
        base_actor: The frozen base actor's state dict (fine-tunes), else None.
        iteration: The iteration it starts at.
        torch_rng: torch's global random state after construction (its stream).
        env_state: Its task copies' state (None: the task cannot save it).
        curve: Its learning curve so far (resumed).
        wall_s: Its training time so far [s].
        total_iterations: Iterations it trains to.
        obs_dim: Observation length.
        num_actions: Actions.

    """

    cfg: dict[str, Any]
    actor: dict[str, torch.Tensor]
    critic: dict[str, torch.Tensor]
    optimizer: dict[str, Any]
    base_actor: dict[str, torch.Tensor] | None
    iteration: int
    torch_rng: torch.Tensor
    env_state: dict[str, Any] | None
    curve: list[dict]
    wall_s: float
    total_iterations: int
    obs_dim: int
    num_actions: int


def lone_start(spec: MemberSpec) -> tuple[MemberStart, Trainer]:
    """Build the member's lone :class:`Trainer` and read where it starts.

    Returns:
        The start, and the trainer (its actor is the template of a member's policy).

    """
    trainer = Trainer(spec.scenario, spec.out_dir, **spec.lone_kwargs())
    alg = trainer.alg
    saved = alg.save()
    start = MemberStart(
        cfg=trainer.cfg,
        actor=saved["actor_state_dict"],
        critic=saved["critic_state_dict"],
        optimizer=saved["optimizer_state_dict"],
        base_actor=None if alg.base_actor is None else alg.base_actor.state_dict(),
        iteration=trainer.runner.current_learning_iteration,
        torch_rng=torch.get_rng_state(),
        env_state=trainer.env.state_dict(),
        curve=list(trainer.curve),
        wall_s=trainer.wall_offset,
        total_iterations=trainer.total_iterations,
        obs_dim=int(trainer.env.obs.shape[-1]),
        num_actions=int(trainer.env.num_actions),
    )
    return start, trainer


def population_config(cfgs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """rsl-rl's config of a population from its members' lone configs.

    The population's model, distribution and algorithm classes, the population size, and
    each member's KL weight and anchor as lists.

    Raises:
        ValueError: The members' configs differ in a setting they must share.

    """
    shared = shared_config(cfgs[0])
    for p, cfg in enumerate(cfgs):
        if shared_config(cfg) != shared:
            raise ValueError(f"member {p} has other training settings than member 0")
    cfg = copy.deepcopy(cfgs[0])
    size = len(cfgs)
    for model in ("actor", "critic"):
        cfg[model]["class_name"] = POPULATION_MODEL
        cfg[model]["population"] = size
    cfg["actor"]["distribution_cfg"]["class_name"] = POPULATION_CATEGORICAL
    algorithm = cfg["algorithm"]
    algorithm["class_name"] = POPULATION_PPO
    algorithm["population"] = size
    for key in MEMBER_ALGORITHM_KEYS:
        algorithm[key] = [member["algorithm"][key] for member in cfgs]
    return cfg


class PopulationMember:
    """One member of a training population, as its ``on_iteration`` callback sees it.

    Attributes:
        population: The :class:`PopulationTrainer`.
        index: The member's index.
        spec: Its job.

    """

    def __init__(self, population: PopulationTrainer, index: int) -> None:
        self.population = population
        self.index = index
        self.spec = population.specs[index]

    @property
    def out_dir(self) -> Path:
        """The member's folder."""
        return self.spec.out_dir

    @property
    def curve(self) -> list[dict]:
        """The member's learning curve so far."""
        return self.population.curves[self.index]

    def policy(self) -> torch.nn.Module:
        """The member's actor now, as a lone rsl-rl ``MLPModel`` on the CPU, in eval mode."""
        return self.population.member_policy(self.index)


class PopulationTrainer:
    """Train ``P`` jobs of one :func:`population_key` together, each as it trains alone.

    Args:
        specs: The jobs (:class:`MemberSpec`), at least one.
        device: Where the networks and PPO's buffers live (``cpu`` or ``cuda``); the
            task copies stay on the CPU (:func:`~amuled_ma.tasks.make_task`).
        progress: Show one tqdm bar for the population.

    Raises:
        ValueError: No jobs, or jobs that cannot train together (another key).

    """

    def __init__(
        self, specs: Sequence[MemberSpec], *, device: str = "cpu", progress: bool = False
    ) -> None:
        torch.set_num_threads(1)
        self.specs = list(specs)
        if not self.specs:
            raise ValueError("a population needs at least one job")
        keys = [population_key(spec) for spec in self.specs]
        for p, key in enumerate(keys):
            if key != keys[0]:
                raise ValueError(
                    f"job {self.specs[p].out_dir} cannot train with {self.specs[0].out_dir}: "
                    "another task, network, run shape or start (see population_key)"
                )
        self.device = device
        self.progress = progress
        self.size = len(self.specs)
        starts: list[MemberStart] = []
        template: torch.nn.Module | None = None
        for spec in self.specs:
            start, trainer = lone_start(spec)
            starts.append(start)
            if template is None:
                template = copy.deepcopy(trainer.alg.get_policy()).cpu()
            del trainer
        assert template is not None
        self.template = template
        self.starts = starts
        self.finetuning = self.specs[0].variant.finetuning  # type: ignore[union-attr]
        shape = self.specs[0].shape()
        self.shape = shape
        self.copies = shape.num_envs
        self.total_iterations = starts[0].total_iterations
        self.cfgs = [start.cfg for start in starts]
        self.cfg = population_config(self.cfgs)
        first = self.specs[0]
        factory = first.task_factory or make_task
        self.task = factory(
            first.scenario,
            self.size * self.copies,
            shaping_coef=shape.shaping_coef,
            seed=first.training_seed,
        )
        feedback = None
        if self.finetuning:
            feedback = MemberFeedback([spec.feedback for spec in self.specs], self.copies)
        self.mdp = BatchedDeliberation(
            self.task, feedback, task_weight=shape.task_weight, feedback_coef=1.0
        )
        self.env = DeliberationVecEnv(
            self.mdp, cfg={"scenario": first.scenario.name, "population": self.size}
        )
        env_states = [start.env_state for start in starts]
        self.env_template = env_states[0]
        own = self.env.state_dict()
        if own is not None and all(state is not None for state in env_states):
            self.env.load_state_dict(stack_env_states(env_states, own))  # type: ignore[arg-type]
        self.runner: OnPolicyRunner = _quiet(
            lambda: OnPolicyRunner(self.env, copy.deepcopy(self.cfg), log_dir=None, device=device)
        )
        self.alg: PopulationPPO = self.runner.alg
        self.alg.actor.load_state_dict(stack_states([start.actor for start in starts]))
        self.alg.critic.load_state_dict(stack_states([start.critic for start in starts]))
        if starts[0].optimizer["state"]:
            self.alg.optimizer.load_state_dict(
                stack_optimizer_states([start.optimizer for start in starts])
            )
        self.alg.streams.set_states([start.torch_rng for start in starts])
        self.runner.current_learning_iteration = starts[0].iteration
        if self.finetuning:
            base = copy.deepcopy(self.alg.get_policy())
            base.load_state_dict(stack_states([start.base_actor for start in starts]))  # type: ignore[misc]
            self.alg.anchor_to(base)
        self.curves = [list(start.curve) for start in starts]
        self.wall_offsets = [start.wall_s for start in starts]
        self.members = [PopulationMember(self, p) for p in range(self.size)]

    # ----------------------------------------------------------------- members
    def member_policy(self, member: int) -> torch.nn.Module:
        """Member ``member``'s actor now, as a lone rsl-rl ``MLPModel`` (CPU, eval mode)."""
        actor = copy.deepcopy(self.template)
        actor.load_state_dict(member_state(self.alg.actor.state_dict(), member))
        actor.eval()
        return actor

    def member_checkpoint(self, member: int, *, completed: bool) -> dict[str, Any]:
        """Member ``member``'s checkpoint as its lone ``Trainer`` writes it."""
        spec, start = self.specs[member], self.starts[member]
        env_state = self.env.state_dict()
        if env_state is not None and self.env_template is not None:
            env_state = member_env_state(env_state, self.env_template, member)
        else:
            env_state = None
        infos = {
            "variant": str(spec.variant),
            "scenario": spec.scenario.name,
            "iteration": self.runner.current_learning_iteration,
            "total_iterations": self.total_iterations,
            "completed": completed,
            "curve": self.curves[member],
            "wall_s": self.wall_offsets[member],
            "torch_rng": self.alg.streams.get_states()[member],
            "env_state": env_state,
            "train_cfg": start.cfg,
            "base_checkpoint": str(spec.base_checkpoint) if spec.base_checkpoint else None,
            "num_actions": start.num_actions,
            "obs_dim": start.obs_dim,
        }
        return {
            "actor_state_dict": _cpu(member_state(self.alg.actor.state_dict(), member)),
            "critic_state_dict": _cpu(member_state(self.alg.critic.state_dict(), member)),
            "optimizer_state_dict": member_optimizer_state(self.alg.optimizer.state_dict(), member),
            "iter": self.runner.current_learning_iteration,
            "infos": infos,
        }

    def save(self, member: int, *, completed: bool) -> Path:
        """Write member ``member``'s ``model_last.pt`` (atomically, as a lone job's)."""
        state = self.member_checkpoint(member, completed=completed)
        path = self.specs[member].out_dir / LAST
        return write_checkpoint(path, lambda tmp: torch.save(state, tmp))

    # ----------------------------------------------------------------- training
    def train(self) -> list[TrainOutcome]:
        """Run (or continue) every member to its configured number of iterations.

        Returns:
            Each member's outcome, in order. On Ctrl-C, SIGTERM or a feedback that stays
            down, every member's checkpoint is written, each resume command printed, and
            the exception re-raised.

        """
        from tqdm.auto import tqdm

        writers: list[Any] = [None] * self.size
        for p, spec in enumerate(self.specs):
            spec.out_dir.mkdir(parents=True, exist_ok=True)
            (spec.out_dir / "train_cfg.json").write_text(json.dumps(self.cfgs[p], indent=2))
            if spec.scenario.output.tensorboard:
                from torch.utils.tensorboard import SummaryWriter

                writers[p] = SummaryWriter(log_dir=str(spec.out_dir / "tb"), flush_secs=30)
        start_it = self.runner.current_learning_iteration
        batch = self.shape.batch
        bar = tqdm(
            total=self.total_iterations,
            initial=start_it,
            desc=f"{self.specs[0].scenario.name}/population of {self.size}",
            unit="it",
            disable=not self.progress,
            dynamic_ncols=True,
            leave=False,
        )
        t0 = time.perf_counter()
        walls = list(self.wall_offsets)
        try:
            for it in range(start_it, self.total_iterations):
                self.alg.set_learning_rate(self.shape.lr_at(it))
                self.runner.learn(1)
                self.runner.current_learning_iteration = it + 1
                self._record(it + 1, batch, walls, time.perf_counter() - t0, writers)
                bar.update(1)
                for p, spec in enumerate(self.specs):
                    if spec.on_iteration is not None:
                        spec.on_iteration(self.members[p], it + 1)
                for p, cfg in enumerate(self.cfgs):
                    if (it + 1) % cfg["save_interval"] == 0 and it + 1 < self.total_iterations:
                        self.save(p, completed=False)
        except (KeyboardInterrupt, AmuledError) as stop:
            bar.close()
            self._stopped(stop)
            raise
        finally:
            for writer in writers:
                if writer is not None:
                    writer.close()
        bar.close()
        wall = time.perf_counter() - t0
        return [self._finish(p, batch, wall) for p in range(self.size)]

    def _record(
        self, it: int, batch: int, walls: list[float], elapsed: float, writers: list[Any]
    ) -> None:
        """Each member's curve row of iteration ``it`` (and its TensorBoard scalars)."""
        losses = self.alg.member_losses
        stats = self.alg.member_rollout_stats()
        episodes = split_episodes(self.env.drain_episodes(), self.size, self.copies)
        for p in range(self.size):
            self.wall_offsets[p] = walls[p] + elapsed
            row = curve_row(
                it, batch, self.wall_offsets[p], self.alg.learning_rate, episodes[p],
                losses[p], stats[p],
            )  # fmt: skip
            self.curves[p].append(row)
            if writers[p] is not None:
                for key, value in row.items():
                    if key not in ("iteration", "env_steps") and value is not None:
                        writers[p].add_scalar(key, value, row["env_steps"])

    def _finish(self, member: int, batch: int, wall: float) -> TrainOutcome:
        """Write member ``member``'s final checkpoint, curve and feedback summary."""
        spec = self.specs[member]
        path = self.save(member, completed=True)
        (spec.out_dir / "curve.json").write_text(json.dumps(self.curves[member]))
        summary = spec.feedback.summary() if spec.feedback is not None else None
        if summary is not None:
            (spec.out_dir / "feedback.json").write_text(json.dumps(summary, indent=2))
        done = self.runner.current_learning_iteration
        return TrainOutcome(
            out_dir=spec.out_dir,
            checkpoint=path,
            iterations=done,
            env_steps=done * batch,
            wall_s=wall,
            curve=self.curves[member],
            feedback=summary,
        )

    def _stopped(self, stop: BaseException) -> None:
        """Keep every member's work after an interruption; print how to resume."""
        hints = [spec.resume_hint for spec in self.specs if spec.resume_hint]
        if isinstance(stop, CheckpointWriteError):
            for hint in hints:
                print(f"\nresume with: {hint}", file=sys.stderr)
            return
        why = (
            "terminated (SIGTERM)"
            if isinstance(stop, Terminated)
            else "interrupted"
            if isinstance(stop, KeyboardInterrupt)
            else "stopped"
        )
        for p in range(self.size):
            self.save(p, completed=False)
        print(
            f"\n{why} at iteration {self.runner.current_learning_iteration}/"
            f"{self.total_iterations}; checkpoints of {self.size} jobs written "
            f"(first: {self.specs[0].out_dir / LAST})",
            file=sys.stderr,
        )
        for hint in hints:
            print(f"resume with: {hint}", file=sys.stderr)


def curve_row(
    it: int,
    batch: int,
    wall_s: float,
    lr: float,
    episodes: list[dict],
    losses: dict,
    extra: dict,
) -> dict[str, Any]:
    """One row of a learning curve, as :class:`Trainer` writes it (``curve.json``)."""
    row: dict[str, Any] = {
        "iteration": it,
        "env_steps": it * batch,
        "wall_s": round(wall_s, 4),
        "charts/lr": lr,
    }
    for key, value in losses.items():
        row[f"losses/{key}"] = float(value) if value is not None and math.isfinite(value) else None
    keys = sorted({k for e in episodes for k in e if k != "env_id"})
    row["charts/episodes"] = len(episodes)
    for key in keys:
        row[f"episode/{key}"] = _mean([e[key] for e in episodes if key in e])
    for key, value in extra.items():
        row[f"feedback/{key}"] = value
    return row


def _cpu(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {key: value.cpu() for key, value in state.items()}


def train_population(
    specs: Sequence[MemberSpec], *, device: str = "cpu", progress: bool = False
) -> list[TrainOutcome]:
    """Train ``specs`` as one population (:class:`PopulationTrainer`); each member's outcome."""
    return PopulationTrainer(specs, device=device, progress=progress).train()
