"""The lone trainer: one job on rsl-rl's own classes, the oracle populations are checked against.

The package trains every job as a population (:mod:`amuled_ma.learn.population`; one job
is a population of one). This is the straightforward loop a population must reproduce
member by member: ``tests/learn/test_population*.py`` train the same jobs here and there
from the same seeds and compare curves, weights, random states and checkpoints.

Base PPO training and fine-tuning on fused feedback, on rsl-rl.

rsl-rl is used through its public API and extension points only. Its
:class:`~rsl_rl.runners.OnPolicyRunner` builds the actor, critic, rollout storage and the
algorithm, which is ours by ``class_name``: :class:`~amuled_ma.learn.anchored_ppo.AnchoredPPO`,
rsl-rl's PPO with the KL anchor of a fine-tune. The environment is the deliberation MDP
(:class:`~amuled_ma.deliberation.mdp.BatchedDeliberation`, wrapped as rsl-rl's ``VecEnv``
by :class:`~amuled_ma.learn.vecenv.DeliberationVecEnv`): the same MDP as the PettingZoo
view. :class:`Trainer` calls ``runner.learn(1)`` once per iteration (rsl-rl's rollout and
update) and adds what a research run needs around it: the learning-rate schedule, a
progress bar, learning curves, Ctrl-C and SIGTERM checkpoints, safe resume.

Base training (paper, Simulation Studies): ``r = r_env + c * r_shaping`` with ``c = 0``
(variant ``base``) or ``c = 1`` (``shaped``); the task computes this sum.

Fine-tuning (paper, eq. "feedback"): a copy of the base policy keeps training on

    r_t = f(B)[a_t] - lambda_KL * (log pi(a_t|s_t) - log pi_base(a_t|s_t))

where ``f(B)`` is the feedback belief for ``s_t`` (the MDP's actor reward,
:func:`~amuled_ma.deliberation.mdp.actor_reward`) and ``pi_base`` the frozen base policy
(the anchor, :class:`~amuled_ma.learn.anchored_ppo.AnchoredPPO`). The bracket is the
per-sample estimator of ``KL(pi || pi_base)``: its expectation over ``a_t ~ pi`` is the KL
divergence, and unlike the closed form it depends on the action, so it tells PPO *which*
actions move the policy away from the base (see docs/learning.md).
"""

from __future__ import annotations

import copy
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

from job_settings import job_shape_of
from rsl_rl.runners import OnPolicyRunner

from amuled_ma.deliberation.feedback_base import Feedback
from amuled_ma.deliberation.mdp import BatchedDeliberation
from amuled_ma.errors import AmuledError, CheckpointError, Terminated
from amuled_ma.learn.anchored_ppo import AnchoredPPO
from amuled_ma.learn.checkpoints import (
    LAST,
    TRAINER_KEYS,
    CheckpointWriteError,
    read_checkpoint,
    write_checkpoints,
)
from amuled_ma.learn.population import TrainOutcome, curve_row
from amuled_ma.learn.population_state import quiet
from amuled_ma.learn.vecenv import DeliberationVecEnv
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import Scenario
from amuled_ma.tasks import make_task

__all__ = ["LAST", "TrainOutcome", "Trainer"]


class Trainer:
    """One PPO training job (base, shaped or fine-tune) writing into ``out_dir``.

    Args:
        scenario: The scenario.
        out_dir: Folder of this variant (created).
        variant: What to train (a :class:`~amuled_ma.records.variants.Variant` or its text,
            ``base``, ``shaped`` or ``finetune:<feedback>``).
        feedback: Feedback of a fine-tune (None for base training).
        base_checkpoint: The base policy a fine-tune starts from and is anchored to.
        resume: Continue from ``out_dir/model_last.pt`` when present.
        seed: Overrides the scenario's seed.
        iterations: Overrides the number of iterations (tests, benchmarks).
        progress: Show a tqdm progress bar.
        resume_hint: The shell command that resumes this job (printed on Ctrl-C).
        on_iteration: Called as ``fn(trainer, iteration)`` after every iteration.
        task_factory: Replaces :func:`make_task` (same signature), e.g. in tests.

    """

    def __init__(
        self,
        scenario: Scenario,
        out_dir: Path,
        *,
        variant: Variant | str = "base",
        feedback: Feedback | None = None,
        base_checkpoint: Path | None = None,
        resume: bool = False,
        seed: int | None = None,
        iterations: int | None = None,
        progress: bool = False,
        resume_hint: str | None = None,
        on_iteration: Callable[[Trainer, int], None] | None = None,
        task_factory: Callable[..., Any] | None = None,
    ) -> None:
        torch.set_num_threads(1)
        self.scenario = scenario
        self.out_dir = Path(out_dir)
        self.variant = Variant.parse(variant)
        self.feedback = feedback
        self.finetuning = self.variant.finetuning
        self.seed = scenario.task.seed if seed is None else seed
        self.progress = progress
        self.resume_hint = resume_hint
        self.on_iteration = on_iteration
        if self.finetuning:
            if feedback is None:
                raise ValueError("a fine-tune needs feedback")
            if base_checkpoint is None or not Path(base_checkpoint).is_file():
                raise CheckpointError(f"base checkpoint not found: {base_checkpoint}")
        # copies, rollout, iterations, learning rate, rsl-rl config: one derivation, shared
        # with the population learner (learn.job_shape)
        shape = job_shape_of(scenario, self.variant, iterations)
        self.num_envs, self.steps_per_env = shape.num_envs, shape.steps_per_env
        self.total_iterations = shape.total_iterations
        self.lr, self.anneal = shape.learning_rate, shape.anneal
        self.cfg = shape.cfg
        self.shaping_coef = shaping = shape.shaping_coef
        torch.manual_seed(self.seed)
        np.random.seed(self.seed % (2**32))
        self.task = (task_factory or make_task)(
            scenario.task, self.num_envs, shaping_coef=shaping, seed=self.seed
        )
        # the deliberation MDP: a fine-tune's feedback answers for all copies at once
        self.mdp = BatchedDeliberation(
            self.task,
            feedback,
            task_weight=shape.task_weight,
            feedback_coef=1.0,
        )
        self.env = DeliberationVecEnv(
            self.mdp, cfg={"scenario": scenario.name, "variant": str(self.variant)}
        )
        # rsl-rl mutates the dict it is given: hand it a copy, keep the original.
        self.runner: OnPolicyRunner = quiet(
            lambda: OnPolicyRunner(self.env, copy.deepcopy(self.cfg), log_dir=None, device="cpu")
        )
        self.alg: AnchoredPPO = self.runner.alg
        self.base_checkpoint = Path(base_checkpoint) if base_checkpoint else None
        self.curve: list[dict] = []
        self.wall_offset = 0.0
        last = self.out_dir / LAST
        if resume and last.is_file():
            self._load_resume(last)
        elif self.finetuning:
            self._init_from_base()
        if self.finetuning:
            self.alg.anchor_to(self._base_actor())

    # ----------------------------------------------------------------- checkpoints
    def _load_state(self, path: Path, load_cfg: dict | None, what: str) -> dict:
        """Load a checkpoint safely (weights only) into rsl-rl's PPO via its public ``load``.

        ``OnPolicyRunner.load`` unpickles with ``weights_only`` off; we read the file with
        :func:`read_checkpoint` and do the runner's two steps ourselves.
        """
        state = read_checkpoint(path, need=TRAINER_KEYS)
        try:
            load_iteration = self.alg.load(state, load_cfg, True)
        except (RuntimeError, KeyError, ValueError) as error:
            raise CheckpointError(
                f"cannot load {what} {path} into the scenario's networks ({error}); was it "
                "trained with other [ppo] hidden dims or another task? Retrain it with --force"
            ) from error
        if load_iteration:
            self.runner.current_learning_iteration = int(state["iter"])
        return state

    def _load_resume(self, path: Path) -> None:
        infos = self._load_state(path, None, "checkpoint").get("infos") or {}
        self.curve = list(infos.get("curve", []))
        self.wall_offset = float(infos.get("wall_s", 0.0))
        if "torch_rng" in infos:
            torch.set_rng_state(infos["torch_rng"])
        if infos.get("env_state") is not None:  # the episodes it stopped in (else: reset)
            try:
                self.env.load_state_dict(infos["env_state"])
            except ValueError as error:
                raise CheckpointError(
                    f"{path}: {error}; it was saved by another task or number of copies "
                    "(retrain with --force)"
                ) from error

    def _init_from_base(self) -> None:
        assert self.base_checkpoint is not None
        load_cfg = {"actor": True, "critic": not self.scenario.finetune.reinit_critic}
        self._load_state(self.base_checkpoint, load_cfg, "base checkpoint")
        self.runner.current_learning_iteration = 0

    def _base_actor(self) -> torch.nn.Module:
        """An actor with the base checkpoint's weights (the fine-tune's anchor)."""
        actor = copy.deepcopy(self.alg.get_policy())
        assert self.base_checkpoint is not None
        state = read_checkpoint(self.base_checkpoint)
        actor.load_state_dict(state["actor_state_dict"])
        return actor

    def save(self, path: Path, *, completed: bool) -> Path:
        """Write a checkpoint with rsl-rl's runner plus our book-keeping in ``infos``."""
        path.parent.mkdir(parents=True, exist_ok=True)
        infos = {
            "variant": str(self.variant),
            "scenario": self.scenario.name,
            "iteration": self.runner.current_learning_iteration,
            "total_iterations": self.total_iterations,
            "completed": completed,
            "curve": self.curve,
            "wall_s": self.wall_offset,
            "torch_rng": torch.get_rng_state(),
            "env_state": self.env.state_dict(),
            "train_cfg": self.cfg,
            "base_checkpoint": str(self.base_checkpoint) if self.base_checkpoint else None,
            "num_actions": self.env.num_actions,
            "obs_dim": int(self.env.obs.shape[-1]),
        }
        # a temp file in the same folder, fsync, atomic rename: a full disk keeps the last one
        return write_checkpoints([(path, lambda tmp: self.runner.save(tmp, infos=infos))])[0]

    # ----------------------------------------------------------------- training
    def _set_lr(self, it: int) -> None:
        lr = self.lr * (1.0 - it / self.total_iterations) if self.anneal else self.lr
        self.alg.set_learning_rate(lr)

    def _iterate(self) -> None:
        """One iteration: rsl-rl's rollout and update (``runner.learn(1)``).

        The runner leaves its iteration counter at the iteration it ran; :meth:`train`
        advances it.
        """
        self.runner.learn(1)

    def train(self) -> TrainOutcome:
        """Run (or continue) the training loop to its configured number of iterations.

        Returns:
            The outcome; on Ctrl-C a checkpoint is written, the resume command printed, and
            :class:`KeyboardInterrupt` re-raised.

        """
        from tqdm.auto import tqdm

        self.out_dir.mkdir(parents=True, exist_ok=True)
        writer = None
        if self.scenario.output.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(log_dir=str(self.out_dir / "tb"), flush_secs=30)
        (self.out_dir / "train_cfg.json").write_text(json.dumps(self.cfg, indent=2))
        start_it = self.runner.current_learning_iteration
        batch = self.num_envs * self.steps_per_env
        bar = tqdm(
            total=self.total_iterations,
            initial=start_it,
            desc=f"{self.scenario.name}/{self.variant}",
            unit="it",
            disable=not self.progress,
            dynamic_ncols=True,
            leave=False,
        )
        t0 = time.perf_counter()
        wall0 = self.wall_offset
        recent: list[dict] = []
        it = start_it
        try:
            for it in range(start_it, self.total_iterations):
                self._set_lr(it)
                self._iterate()
                self.runner.current_learning_iteration = it + 1
                losses = self.alg.last_losses
                (extra,) = self.alg.member_rollout_stats()
                self.wall_offset = wall0 + time.perf_counter() - t0
                episodes = self.env.drain_episodes()
                recent = (recent + episodes)[-100:]
                row = curve_row(
                    it + 1, batch, self.wall_offset, self.alg.learning_rate, episodes, losses, extra
                )
                self.curve.append(row)
                if writer is not None:
                    for key, value in row.items():
                        if key not in ("iteration", "env_steps") and value is not None:
                            writer.add_scalar(key, value, row["env_steps"])
                if self.on_iteration is not None:
                    self.on_iteration(self, it + 1)
                bar.update(1)
                if self.progress and recent:
                    fields = getattr(self.feedback, "progress", None)  # asked=13/131
                    extra_fields = fields() if callable(fields) else {}
                    bar.set_postfix(
                        ret=f"{np.mean([e['return'] for e in recent]):.2f}",
                        **extra_fields,
                        refresh=False,
                    )
                if (it + 1) % self.cfg["save_interval"] == 0 and it + 1 < self.total_iterations:
                    self.save(self.out_dir / LAST, completed=False)
        except (KeyboardInterrupt, AmuledError) as stop:
            # Ctrl-C, or a belief backend that stayed down after its retries: keep the work.
            bar.close()
            if isinstance(stop, CheckpointWriteError):
                # the disk is full (or the folder gone): the last checkpoint on disk is kept
                if self.resume_hint:
                    print(f"\nresume with: {self.resume_hint}", file=sys.stderr)
                raise
            path = self.save(self.out_dir / LAST, completed=False)
            why = (
                "terminated (SIGTERM)"
                if isinstance(stop, Terminated)
                else "interrupted"
                if isinstance(stop, KeyboardInterrupt)
                else "stopped"
            )
            print(
                f"\n{why} at iteration {self.runner.current_learning_iteration}/"
                f"{self.total_iterations}; checkpoint written to {path}",
                file=sys.stderr,
            )
            if self.resume_hint:
                print(f"resume with: {self.resume_hint}", file=sys.stderr)
            raise
        finally:
            if writer is not None:
                writer.close()
        bar.close()
        path = self.save(self.out_dir / LAST, completed=True)
        (self.out_dir / "curve.json").write_text(json.dumps(self.curve))
        summary = self.feedback.summary() if self.feedback is not None else None
        if summary is not None:
            (self.out_dir / "feedback.json").write_text(json.dumps(summary, indent=2))
        return TrainOutcome(
            out_dir=self.out_dir,
            checkpoint=path,
            iterations=self.runner.current_learning_iteration,
            env_steps=self.runner.current_learning_iteration * batch,
            wall_s=time.perf_counter() - t0,
            curve=self.curve,
            feedback=summary,
        )

    def policy(self) -> torch.nn.Module:
        """Return the trained actor (an rsl-rl ``MLPModel``) in eval mode."""
        self.alg.eval_mode()
        return self.alg.get_policy()
