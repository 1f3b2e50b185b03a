"""Training: every job trains here, P jobs of one shape together, each as it trains alone.

A job alone is a population of one on the lone rsl-rl classes; each member starts and ends
as its lone run would (docs/learning.md, "Population training").
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

from rsl_rl.runners import OnPolicyRunner

from amuled_ma.deliberation.mdp import MemberFeedback
from amuled_ma.errors import AmuledError, MemberFailed, Terminated
from amuled_ma.files.safe import FileWriteError, write_text_atomic
from amuled_ma.learn.anchored_ppo import AnchoredPPO
from amuled_ma.learn.checkpoints import LAST, CheckpointWriteError, write_checkpoints
from amuled_ma.learn.population_groups import MemberSpec, population_config, population_key
from amuled_ma.learn.population_models import member_state, stack_states
from amuled_ma.learn.population_ppo import PopulationPPO
from amuled_ma.learn.population_state import (
    MemberStart,
    lone_start,
    member_env,
    member_env_state,
    member_optimizer_state,
    quiet,
    split_episodes,
    stack_env_states,
    stack_optimizer_states,
)
from amuled_ma.learn.vecenv import DeliberationVecEnv
from amuled_ma.monitor.progress import Progress
from amuled_ma.monitor.tensorboard_log import TensorBoardLog

__all__ = ["LAST", "PopulationMember", "PopulationTrainer", "TrainOutcome", "train_population"]


@dataclass
class TrainOutcome:
    """What training one job produced; ``completed`` is False when interrupted."""

    out_dir: Path
    checkpoint: Path
    iterations: int
    env_steps: int
    wall_s: float
    completed: bool = True
    curve: list[dict] = field(default_factory=list)
    feedback: dict | None = None


class PopulationMember:
    """One member of a training population, as its ``on_iteration`` callback sees it."""

    def __init__(self, population: PopulationTrainer, index: int) -> None:
        self.population = population
        self.index = index
        self.spec = population.specs[index]
        self.out_dir: Path = self.spec.out_dir
        #: The member's learning curve so far (the list the trainer appends to).
        self.curve: list[dict] = population.curves[index]

    def policy(self) -> torch.nn.Module:
        """The member's actor now, as a lone rsl-rl ``MLPModel`` on the CPU, in eval mode."""
        return self.population.member_policy(self.index)


class PopulationTrainer:
    """Train ``P`` jobs of one `population_key` together, each as it trains alone.

    ``device`` holds the networks and PPO's buffers (the task copies stay on the CPU);
    ``progress`` shows one tqdm bar. Raises ValueError: a job of another key.
    """

    def __init__(
        self, specs: Sequence[MemberSpec], *, device: str = "cpu", progress: bool = False
    ) -> None:
        torch.set_num_threads(1)
        self.specs = list(specs)
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
        self.finetuning = self.specs[0].variant.finetuning
        self.shape = self.specs[0].shape()
        self.copies = self.shape.num_envs
        # one member on the CPU: its own lone runner (rsl-rl's classes: its numbers, its speed)
        self.stacked = self.size > 1 or torch.device(device).type != "cpu"
        starts: list[MemberStart] = []
        for spec in self.specs:
            start, runner, env = lone_start(spec)
            starts.append(start)
            if len(starts) == 1:  # the template of a member's lone actor
                self.template = copy.deepcopy(runner.alg.get_policy()).cpu()
        self.total_iterations = self.shape.total_iterations
        self.cfgs = [spec.shape().cfg for spec in self.specs]
        self.cfg = population_config(self.cfgs) if self.stacked else copy.deepcopy(self.cfgs[0])
        if self.stacked:
            self.env = self._population_env(starts)
            self.runner: OnPolicyRunner = quiet(
                lambda: OnPolicyRunner(
                    self.env, copy.deepcopy(self.cfg), log_dir=None, device=device
                )
            )
            self._load_members(starts)
        else:  # the lone runner as built, its weights, state and random stream loaded
            self.env, self.runner = env, runner
        self.mdp, self.env_template = self.env.mdp, starts[0].env_state
        self.alg: AnchoredPPO = self.runner.alg
        if self.finetuning:  # every member's base actor, frozen
            base = copy.deepcopy(self.alg.get_policy())
            bases = [start.base_actor or {} for start in starts]
            base.load_state_dict(stack_states(bases) if self.stacked else dict(bases[0]))
            self.alg.anchor_to(base)
        self.curves = [list(start.curve) for start in starts]
        self.wall_offsets = [start.wall_s for start in starts]
        self.sizes = [(start.obs_dim, start.num_actions) for start in starts]
        self.members = [PopulationMember(self, p) for p in range(self.size)]
        #: The state after the last whole iteration (`population_state`, cloned), what a
        #: stop writes; ``before``: the one before it, what a failed member keeps.
        self.snapshot: dict[str, Any] = self.population_state(copy_now=True)
        self.before = self.snapshot

    def _population_env(self, starts: list[MemberStart]) -> DeliberationVecEnv:
        """One task of ``P x E`` copies in the states the members' runs left (if it saves them)."""
        first = self.specs[0]
        feedback = None
        if self.finetuning:
            feedback = MemberFeedback([spec.feedback for spec in self.specs], self.copies)
        cfg = {"scenario": first.scenario.name, "population": self.size}
        env = member_env(first, self.size * self.copies, feedback, cfg)
        states = [start.env_state for start in starts]
        own = env.state_dict()
        if own is not None and all(state is not None for state in states):
            env.load_state_dict(stack_env_states(states, own))  # type: ignore[arg-type]
        return env

    def _load_members(self, starts: list[MemberStart]) -> None:
        """Load every member's weights, Adam state, random stream and iteration."""
        alg = self.runner.alg
        assert isinstance(alg, PopulationPPO)
        alg.actor.load_state_dict(stack_states([start.actor for start in starts]))
        alg.critic.load_state_dict(stack_states([start.critic for start in starts]))
        if starts[0].optimizer["state"]:
            alg.optimizer.load_state_dict(stack_optimizer_states([s.optimizer for s in starts]))
        alg.streams.set_states([start.torch_rng for start in starts])
        self.runner.current_learning_iteration = starts[0].iteration

    def _member(self, state: dict[str, torch.Tensor], member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s lone model state (`member_state`)."""
        if self.stacked:
            return member_state(state, member)
        return {key: value.clone() for key, value in state.items()}

    def _streams(self) -> list[torch.Tensor]:
        """Each member's random state (a lone job draws from torch's global generator)."""
        if isinstance(self.alg, PopulationPPO):
            return self.alg.streams.get_states()
        return [torch.get_rng_state()]

    def member_policy(self, member: int) -> torch.nn.Module:
        """Member ``member``'s actor now, as a lone rsl-rl ``MLPModel`` (CPU, eval mode)."""
        actor = copy.deepcopy(self.template)
        actor.load_state_dict(self._member(self.alg.actor.state_dict(), member))
        actor.eval()
        return actor

    def member_checkpoint(
        self, member: int, *, completed: bool, shared: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """Member ``member``'s checkpoint, in the format of a job alone.

        ``shared``: the population's `population_state`, read once for several members.
        """
        spec, (obs_dim, num_actions) = self.specs[member], self.sizes[member]
        state = shared or self.population_state()
        env_state = None
        if state["env"] is not None and self.env_template is not None:
            env_state = member_env_state(state["env"], self.env_template, member)
        iteration = state["iteration"]
        infos = {
            "variant": str(spec.variant),
            "scenario": spec.scenario.name,
            "iteration": iteration,
            "total_iterations": self.total_iterations,
            "completed": completed,
            "curve": self.curves[member][: state["rows"][member]],
            "wall_s": state["walls"][member],
            "torch_rng": state["rng"][member],
            "env_state": env_state,
            "train_cfg": self.cfgs[member],
            "base_checkpoint": str(spec.base_checkpoint) if spec.base_checkpoint else None,
            "num_actions": num_actions,
            "obs_dim": obs_dim,
        }
        return {
            "actor_state_dict": _cpu(self._member(state["actor"], member)),
            "critic_state_dict": _cpu(self._member(state["critic"], member)),
            "optimizer_state_dict": member_optimizer_state(
                state["optimizer"], member if self.stacked else None
            ),
            "iter": iteration,
            "infos": infos,
        }

    def population_state(self, *, copy_now: bool = False) -> dict[str, Any]:
        """Everything a member's checkpoint holds, read once for all members.

        ``copy_now`` clones every tensor (a `snapshot`); else the live tensors.
        """
        state = {
            "actor": self.alg.actor.state_dict(),
            "critic": self.alg.critic.state_dict(),
            "optimizer": self.alg.optimizer.state_dict(),
            "env": self.env.state_dict(),  # cloned by the env
            "iteration": self.runner.current_learning_iteration,
            "rng": self._streams(),  # new tensors
            "walls": list(self.wall_offsets),
            "rows": [len(curve) for curve in self.curves],
        }
        if copy_now:
            for key in ("actor", "critic", "optimizer"):
                state[key] = copy.deepcopy(state[key])
        return state

    def save_states(
        self, members: Sequence[tuple[int, dict[str, Any]]], *, completed: bool
    ) -> list[Path]:
        """Write ``(member, population_state)`` checkpoints as one set (all or none replaced)."""
        writes = []
        for p, state in members:
            checkpoint = self.member_checkpoint(p, completed=completed, shared=state)
            writes.append((self.specs[p].out_dir / LAST, functools.partial(torch.save, checkpoint)))
        return write_checkpoints(writes)

    def iterate(self) -> None:
        """One iteration of every member: rsl-rl's rollout and update (``runner.learn(1)``)."""
        self.runner.learn(1)

    def train(self) -> list[TrainOutcome]:
        """Run (or continue) every member to its configured iterations; each member's outcome.

        On Ctrl-C, SIGTERM or a feedback that stays down, every checkpoint is written and re-raised.
        """
        writers: list[TensorBoardLog | None] = [None] * self.size
        for p, spec in enumerate(self.specs):
            spec.out_dir.mkdir(parents=True, exist_ok=True)
            write_text_atomic(spec.out_dir / "train_cfg.json", json.dumps(self.cfgs[p], indent=2))
            if spec.scenario.output.tensorboard:
                writers[p] = TensorBoardLog(spec.out_dir / "tb", flush_secs=30)
        start_it = self.runner.current_learning_iteration
        batch = self.shape.batch
        bar = Progress(
            f"{self.specs[0].scenario.name}/"
            + (f"population of {self.size}" if self.size > 1 else str(self.specs[0].variant)),
            self.total_iterations,
            bar=self.progress,
            initial=start_it,
            unit="it",
        )
        t0 = time.perf_counter()
        walls = list(self.wall_offsets)
        try:
            for it in range(start_it, self.total_iterations):
                self.alg.set_learning_rate(self.shape.lr_at(it))
                self.iterate()
                self.runner.current_learning_iteration = it + 1
                self._record(it + 1, batch, walls, time.perf_counter() - t0, writers)
                self.before, self.snapshot = self.snapshot, self.population_state(copy_now=True)
                bar.update(1)
                for p, spec in enumerate(self.specs):
                    if spec.on_iteration is not None:
                        spec.on_iteration(self.members[p], it + 1)
                self._check_members()
                due = [
                    p
                    for p, cfg in enumerate(self.cfgs)
                    if (it + 1) % cfg["save_interval"] == 0 and it + 1 < self.total_iterations
                ]
                self.save_states([(p, self.snapshot) for p in due], completed=False)
        except MemberFailed as failed:
            bar.close()
            raise self._member_failed(failed) from failed
        except (KeyboardInterrupt, AmuledError) as stop:
            bar.close()
            self._stopped(stop)
            raise
        finally:
            bar.close()  # whatever ends the loop: no watcher thread outlives it
            # a failed flush must not hide the exception already on its way out
            quiet = (FileWriteError,) if sys.exc_info()[0] is not None else ()
            for writer in filter(None, writers):
                with contextlib.suppress(*quiet):
                    writer.close()
        wall = time.perf_counter() - t0
        now = self.population_state()
        paths = self.save_states([(p, now) for p in range(self.size)], completed=True)
        return [self._finish(p, path, batch, wall) for p, path in enumerate(paths)]

    def _record(
        self,
        it: int,
        batch: int,
        walls: list[float],
        elapsed: float,
        writers: list[TensorBoardLog | None],
    ) -> None:
        """Each member's curve row of iteration ``it`` (and its TensorBoard scalars)."""
        losses, stats = self.alg.member_losses, self.alg.member_rollout_stats()
        episodes = split_episodes(self.env.drain_episodes(), self.size, self.copies)
        for p in range(self.size):
            self.wall_offsets[p] = walls[p] + elapsed
            row = curve_row(
                it, batch, self.wall_offsets[p], self.alg.learning_rate, episodes[p],
                losses[p], stats[p],
            )  # fmt: skip
            self.curves[p].append(row)
            writer = writers[p]
            if writer is not None:
                for key, value in row.items():
                    if key not in ("iteration", "env_steps") and value is not None:
                        writer.add_scalar(key, value, row["env_steps"])

    def _finish(self, member: int, path: Path, batch: int, wall: float) -> TrainOutcome:
        """Write member ``member``'s curve and feedback summary; its outcome."""
        spec = self.specs[member]
        write_text_atomic(spec.out_dir / "curve.json", json.dumps(self.curves[member]))
        summary = spec.feedback.summary() if spec.feedback is not None else None
        if summary is not None:
            write_text_atomic(spec.out_dir / "feedback.json", json.dumps(summary, indent=2))
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

    def _check_members(self) -> None:
        """Raise `MemberFailed` for the first member whose feedback or gradient failed."""
        feedback = self.mdp.feedback
        failures = dict(feedback.failures) if isinstance(feedback, MemberFeedback) else {}
        for member in self.alg.failed_members():
            failures.setdefault(member, "its gradient was not a finite number (NaN or inf)")
        if failures:
            member = min(failures)
            raise MemberFailed(member, failures[member])

    def _member_failed(self, failed: MemberFailed) -> MemberFailed:
        """Write every member's checkpoint (the failed one's before the iteration); the failure."""
        member = failed.member
        others = [p for p in range(self.size) if p != member]
        pairs = [(p, self.snapshot) for p in others] + [(member, self.before)]
        self.save_states(pairs, completed=False)
        spec = self.specs[member]
        go_on = ""
        if others:
            go_on = f", and the {len(others)} other member(s) of its population go on without it"
        elif spec.resume_hint:
            print(f"\nresume with: {spec.resume_hint}", file=sys.stderr)
        return MemberFailed(
            member,
            f"{spec.out_dir}: stopped in iteration {self.snapshot['iteration']}/"
            f"{self.total_iterations}: {failed}; its checkpoint of iteration "
            f"{self.before['iteration']} is written{go_on}",
        )

    def _stopped(self, stop: BaseException) -> None:
        """Keep every member's work after an interruption; print how to resume."""
        # one line per command: the jobs of one sweep share theirs
        hints = list(dict.fromkeys(spec.resume_hint for spec in self.specs if spec.resume_hint))
        if isinstance(stop, CheckpointWriteError):
            for hint in hints:
                print(f"\nresume with: {hint}", file=sys.stderr)
            return
        why = "stopped"
        if isinstance(stop, KeyboardInterrupt):
            why = "terminated (SIGTERM)" if isinstance(stop, Terminated) else "interrupted"
        # the state after the last whole iteration: a stop inside one resumes as if it never began
        self.save_states([(p, self.snapshot) for p in range(self.size)], completed=False)
        first = self.specs[0].out_dir / LAST
        written = (
            f"checkpoints of {self.size} jobs written (first: {first})"
            if self.size > 1
            else f"checkpoint written to {first}"
        )
        print(
            f"\n{why} at iteration {self.snapshot['iteration']}/{self.total_iterations}; "
            + written,
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
    """One ``curve.json`` row for iteration ``it`` (1-based): its episodes, losses, ``extra``."""
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
        values = [e[key] for e in episodes if key in e]
        row[f"episode/{key}"] = float(np.mean(values)) if values else None
    for key, value in extra.items():
        row[f"feedback/{key}"] = value
    return row


def _cpu(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {key: value.cpu() for key, value in state.items()}


def train_population(
    specs: Sequence[MemberSpec],
    *,
    device: str = "cpu",
    progress: bool = False,
    announce: bool = True,
) -> list[TrainOutcome | MemberFailed]:
    """Train ``specs`` as one population; per job a `TrainOutcome` or the `MemberFailed`.

    A failed member stops alone: the others' checkpoints are written, one line names it
    (with ``announce``), and the others go on as a population without it.
    """
    specs = list(specs)
    results: dict[int, TrainOutcome | MemberFailed] = {}
    remaining = list(range(len(specs)))
    while remaining:
        trainer = PopulationTrainer([specs[i] for i in remaining], device=device, progress=progress)
        try:
            outcomes = trainer.train()
        except MemberFailed as failed:
            results[remaining.pop(failed.member)] = failed
            if announce:
                print(f"amuled: a member of a population failed: {failed}", file=sys.stderr)
            specs = [dataclasses.replace(spec, resume=True) for spec in specs]
            continue
        results.update(zip(remaining, outcomes, strict=True))
        remaining = []
    return [results[i] for i in range(len(specs))]
