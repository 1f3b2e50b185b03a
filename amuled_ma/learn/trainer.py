"""Training loops: base PPO training and fine-tuning on fused feedback, on rsl-rl.

rsl-rl is used as a library: its :class:`~rsl_rl.runners.OnPolicyRunner` builds the
actor, critic, rollout storage and :class:`~rsl_rl.algorithms.PPO`, and saves and loads
checkpoints; we drive the iteration loop ourselves (a readable, CleanRL-style loop)
because fine-tuning has to compute the reward from the policy itself, and because we
want a progress bar, Ctrl-C checkpoints and learning curves.

Base training (paper, Simulation Studies): ``r = r_env + c * r_shaping`` with ``c = 0``
(variant ``base``) or ``c = 1`` (``shaped``); the task computes this sum.

Fine-tuning (paper, eq. "feedback"): a copy of the base policy keeps training on

    r_t = f(B)[a_t] - lambda_KL * (log pi(a_t|s_t) - log pi_base(a_t|s_t))

where ``f(B)`` is the feedback belief for ``s_t`` and ``pi_base`` the frozen base policy.
The bracket is the per-sample estimator of ``KL(pi || pi_base)``: its expectation over
``a_t ~ pi`` is the KL divergence, and unlike the closed form it depends on the action,
so it tells PPO *which* actions move the policy away from the base (see docs/learning.md).
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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

from rsl_rl.runners import OnPolicyRunner

from amuled_ma.errors import AmuledError, CheckpointError, ScenarioError, Terminated
from amuled_ma.learn import fast_ppo
from amuled_ma.learn.anchors import EpisodeWindowKL, per_sample_kl
from amuled_ma.learn.checkpoints import TRAINER_KEYS, read_checkpoint
from amuled_ma.learn.config import rsl_rl_config
from amuled_ma.learn.distribution import orthogonal_init
from amuled_ma.learn.fast_ppo import ppo_update
from amuled_ma.learn.feedback import Feedback
from amuled_ma.learn.vecenv import OBS_GROUP, TaskVecEnv
from amuled_ma.scenario import Scenario

#: Name of the newest checkpoint in a variant folder.
LAST = "model_last.pt"


def make_task(scenario: Scenario, num_envs: int, *, shaping_coef: float, seed: int) -> Any:
    """Instantiate the scenario's batched task.

    Args:
        scenario: The scenario.
        num_envs: Number of copies.
        shaping_coef: ``c`` of the reward ``r_env + c * r_shaping``.
        seed: Seed of the task's RNG.

    """
    from amuled_ma.tasks import get_task

    cls = get_task(scenario.task.name)
    kwargs: dict[str, Any] = dict(scenario.task.options)
    if scenario.task.max_steps:
        kwargs["max_steps"] = scenario.task.max_steps
    return cls(num_envs, device="cpu", seed=seed, shaping_coef=shaping_coef, **kwargs)


def kl_reward(logp: torch.Tensor, logp_base: torch.Tensor, lambda_kl: float) -> torch.Tensor:
    """Per-sample KL penalty ``-lambda_KL * (log pi(a|s) - log pi_base(a|s))``.

    Args:
        logp: Log-probability of the taken actions under the trained policy ``[N]``.
        logp_base: Log-probability of the same actions under the frozen base ``[N]``.
        lambda_kl: Weight of the anchor.

    Returns:
        The reward term ``[N]``.

    """
    return -lambda_kl * per_sample_kl(logp, logp_base)


def action_log_probs(actor: torch.nn.Module, obs: torch.Tensor) -> torch.Tensor:
    """Return ``log pi(.|s)`` ``[N, A]`` of an rsl-rl MLP actor with our categorical head."""
    return torch.log_softmax(fast_ppo.mlp_forward(actor.mlp, actor.obs_normalizer(obs)), dim=-1)


def make_optimizer(alg: Any, lr: float) -> torch.optim.Optimizer:
    """Adam over actor and critic as CleanRL (``eps = 1e-5``), fused where torch has it.

    rsl-rl builds a plain ``torch.optim.Adam``; on CPU with small nets the per-parameter
    Python loop of that implementation is a large part of an update, and the fused kernel
    is about 3x faster (measured on FindMilk updates).
    """
    params = [*alg.actor.parameters(), *alg.critic.parameters()]
    try:
        return torch.optim.Adam(params, lr=lr, eps=1e-5, fused=True)
    except (RuntimeError, TypeError):  # pragma: no cover - older torch or device
        return torch.optim.Adam(params, lr=lr, eps=1e-5, foreach=True)


@dataclass
class TrainOutcome:
    """What a training call produced.

    Attributes:
        out_dir: The variant's folder (checkpoints, curve, TensorBoard).
        checkpoint: Path of the final (or interrupt) checkpoint.
        iterations: Iterations completed in total.
        env_steps: Environment steps in total.
        wall_s: Wall-clock seconds of this call.
        completed: False when interrupted.
        curve: Per-iteration rows (learning curve).
        feedback: Feedback diagnostics (fine-tuning only).

    """

    out_dir: Path
    checkpoint: Path
    iterations: int
    env_steps: int
    wall_s: float
    completed: bool = True
    curve: list[dict] = field(default_factory=list)
    feedback: dict | None = None


def _quiet(fn: Callable[[], Any]) -> Any:
    with contextlib.redirect_stdout(io.StringIO()):
        return fn()


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


class Trainer:
    """One PPO training job (base, shaped or fine-tune) writing into ``out_dir``.

    Args:
        scenario: The scenario.
        out_dir: Folder of this variant (created).
        variant: ``base``, ``shaped`` or ``finetune:<feedback>``.
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
        variant: str = "base",
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
        self.variant = variant
        self.feedback = feedback
        self.finetuning = variant.startswith("finetune")
        self.seed = scenario.task.seed if seed is None else seed
        self.progress = progress
        self.resume_hint = resume_hint
        self.on_iteration = on_iteration
        ppo = scenario.ppo
        if self.finetuning:
            ft = scenario.finetune
            if feedback is None:
                raise ValueError("a fine-tune needs feedback")
            if base_checkpoint is None or not Path(base_checkpoint).is_file():
                raise CheckpointError(f"base checkpoint not found: {base_checkpoint}")
            self.num_envs, self.steps_per_env = ft.num_envs, ft.num_steps_per_env
            self.total_iterations = ft.iterations if iterations is None else iterations
            self.lr, self.anneal = ft.learning_rate, ft.anneal_lr
            self.cfg = rsl_rl_config(
                ppo,
                num_steps_per_env=ft.num_steps_per_env,
                learning_rate=ft.learning_rate,
                num_learning_epochs=ft.num_learning_epochs,
                save_interval=ft.save_interval,
            )
            shaping = 0.0
        else:
            base = scenario.base
            self.num_envs, self.steps_per_env = base.num_envs, base.num_steps_per_env
            batch = base.num_envs * base.num_steps_per_env
            self.total_iterations = (
                max(1, base.total_steps // batch) if iterations is None else iterations
            )
            self.lr, self.anneal = ppo.learning_rate, ppo.anneal_lr
            self.cfg = rsl_rl_config(
                ppo, num_steps_per_env=base.num_steps_per_env, save_interval=base.save_interval
            )
            shaping = base.shaping_coef if variant == "shaped" else 0.0
        self.shaping_coef = shaping
        section = "finetune" if self.finetuning else "base"
        minibatch = self.num_envs * self.steps_per_env // ppo.num_mini_batches
        if ppo.normalize_advantage_per_mini_batch and minibatch < 2:
            raise ScenarioError(
                f"{scenario.path or scenario.name}: [{section}] num_envs x num_steps_per_env = "
                f"{self.num_envs * self.steps_per_env} transitions split into "
                f"[ppo] num_mini_batches = {ppo.num_mini_batches} gives mini-batches of "
                f"{minibatch}; per-mini-batch advantage normalisation needs at least 2 "
                "(raise num_envs or num_steps_per_env)"
            )
        torch.manual_seed(self.seed)
        np.random.seed(self.seed % (2**32))
        self.task = (task_factory or make_task)(
            scenario, self.num_envs, shaping_coef=shaping, seed=self.seed
        )
        self.env = TaskVecEnv(self.task, cfg={"scenario": scenario.name, "variant": variant})
        # rsl-rl mutates the dict it is given: hand it a copy, keep the original.
        self.runner: OnPolicyRunner = _quiet(
            lambda: OnPolicyRunner(self.env, copy.deepcopy(self.cfg), log_dir=None, device="cpu")
        )
        self.alg = self.runner.alg
        orthogonal_init(self.alg.critic.mlp, last_std=1.0)
        self.alg.optimizer = make_optimizer(self.alg, self.lr)
        self.base_actor: torch.nn.Module | None = None
        self.base_checkpoint = Path(base_checkpoint) if base_checkpoint else None
        self.curve: list[dict] = []
        self.wall_offset = 0.0
        last = self.out_dir / LAST
        if resume and last.is_file():
            self._load_resume(last)
        elif self.finetuning:
            self._init_from_base()
        if self.finetuning:
            self.base_actor = self._frozen_base()
        #: the authors' recipe keeps each copy's window of taken-action log-probabilities
        self.window: EpisodeWindowKL | None = (
            EpisodeWindowKL(self.num_envs, self.steps_per_env)
            if self.finetuning and scenario.finetune.recipe == "authors"
            else None
        )

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

    def _init_from_base(self) -> None:
        assert self.base_checkpoint is not None
        load_cfg = {"actor": True, "critic": not self.scenario.finetune.reinit_critic}
        self._load_state(self.base_checkpoint, load_cfg, "base checkpoint")
        self.runner.current_learning_iteration = 0

    def _frozen_base(self) -> torch.nn.Module:
        actor = copy.deepcopy(self.alg.get_policy())
        assert self.base_checkpoint is not None
        state = read_checkpoint(self.base_checkpoint)
        actor.load_state_dict(state["actor_state_dict"])
        actor.eval()
        for p in actor.parameters():
            p.requires_grad_(False)
        return actor

    def save(self, path: Path, *, completed: bool) -> Path:
        """Write a checkpoint with rsl-rl's runner plus our book-keeping in ``infos``."""
        path.parent.mkdir(parents=True, exist_ok=True)
        infos = {
            "variant": self.variant,
            "scenario": self.scenario.name,
            "iteration": self.runner.current_learning_iteration,
            "total_iterations": self.total_iterations,
            "completed": completed,
            "curve": self.curve,
            "wall_s": self.wall_offset,
            "torch_rng": torch.get_rng_state(),
            "train_cfg": self.cfg,
            "base_checkpoint": str(self.base_checkpoint) if self.base_checkpoint else None,
            "num_actions": self.env.num_actions,
            "obs_dim": int(self.env.obs.shape[-1]),
        }
        tmp = path.with_suffix(".tmp")
        self.runner.save(str(tmp), infos=infos)
        tmp.replace(path)
        return path

    # ----------------------------------------------------------------- training
    def _set_lr(self, it: int) -> None:
        lr = self.lr * (1.0 - it / self.total_iterations) if self.anneal else self.lr
        self.alg.learning_rate = lr
        for group in self.alg.optimizer.param_groups:
            group["lr"] = lr

    def _feedback_and_anchor(
        self, state: torch.Tensor, index: torch.Tensor, logp: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The feedback ``f(B)[a_t]`` and the KL anchor of the recipe, per copy ``[N]``.

        Called before the env step (the feedback is for the state the action was taken in).
        """
        assert self.feedback is not None and self.base_actor is not None
        beliefs = torch.as_tensor(self.feedback(state, self.task), dtype=torch.float32)
        fb = beliefs.gather(1, index.unsqueeze(1)).squeeze(1)
        logp_base = action_log_probs(self.base_actor, state).gather(1, index.unsqueeze(1))
        if self.window is not None:
            anchor = self.window.step(logp, logp_base.squeeze(1))
        else:
            anchor = per_sample_kl(logp, logp_base.squeeze(1))
        return fb, anchor

    def _finetune_reward(
        self,
        fb: torch.Tensor,
        anchor: torch.Tensor,
        r_task: torch.Tensor,
        dones: torch.Tensor,
        extras: dict[str, Any],
    ) -> torch.Tensor:
        """``f(B)[a] - lambda_KL * anchor (+ env_reward_coef * r_env)``, after the env step."""
        ft = self.scenario.finetune
        rewards = fb - ft.lambda_kl * anchor
        if ft.env_reward_coef:
            r_env = extras["info"].get("r_env", r_task)
            rewards = rewards + ft.env_reward_coef * torch.as_tensor(r_env).float()
        if self.window is not None:
            self.window.end_episodes(dones)
        return rewards

    def _rollout(self) -> dict[str, Any]:
        if not fast_ppo.supports(self.alg):
            return self._rollout_rsl_rl()
        alg, env = self.alg, self.env
        state = env.obs
        fb_sum, kl_sum, n = 0.0, 0.0, 0
        if self.window is not None:
            self.window.start_iteration()
        with torch.inference_mode():
            for _ in range(self.steps_per_env):
                actions, values, logp, log_probs = fast_ppo.act(alg, state)
                index = actions.argmax(dim=-1)
                if self.finetuning:
                    fb, anchor = self._feedback_and_anchor(state, index, logp)
                    obs, r_task, dones, extras = env.step_tensors(index)
                    rewards = self._finetune_reward(fb, anchor, r_task, dones, extras)
                    fb_sum += float(fb.sum())
                    kl_sum += float(anchor.sum())
                    n += len(index)
                else:
                    obs, rewards, dones, extras = env.step_tensors(index)
                fast_ppo.record(
                    alg, state, actions, values, logp, log_probs, rewards, dones,
                    extras["time_outs"],
                )  # fmt: skip
                state = obs
            alg.compute_returns(env.get_observations())
        out: dict[str, Any] = {}
        if n:
            out["feedback_reward"] = fb_sum / n
            out["kl"] = kl_sum / n
        return out

    def _rollout_rsl_rl(self) -> dict[str, Any]:
        alg, env = self.alg, self.env
        obs = env.get_observations()
        fb_sum, kl_sum, n = 0.0, 0.0, 0
        if self.window is not None:
            self.window.start_iteration()
        with torch.inference_mode():
            for _ in range(self.steps_per_env):
                state = obs[OBS_GROUP]
                actions = alg.act(obs)
                index = actions.argmax(dim=-1)
                if self.finetuning:
                    logp = alg.transition.actions_log_prob.reshape(-1)
                    fb, anchor = self._feedback_and_anchor(state, index, logp)
                    obs, r_task, dones, extras = env.step(index)
                    rewards = self._finetune_reward(fb, anchor, r_task, dones, extras)
                    fb_sum += float(fb.sum())
                    kl_sum += float(anchor.sum())
                    n += len(index)
                else:
                    obs, rewards, dones, extras = env.step(index)
                alg.process_env_step(obs, rewards, dones, extras)
            alg.compute_returns(obs)
        out: dict[str, Any] = {}
        if n:
            out["feedback_reward"] = fb_sum / n
            out["kl"] = kl_sum / n
        return out

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
            self.alg.train_mode()
            for it in range(start_it, self.total_iterations):
                self._set_lr(it)
                extra = self._rollout()
                losses = ppo_update(self.alg)  # = self.alg.update(), bit for bit, leaner
                self.runner.current_learning_iteration = it + 1
                self.wall_offset = wall0 + time.perf_counter() - t0
                episodes = self.env.drain_episodes()
                recent = (recent + episodes)[-100:]
                row = self._curve_row(it + 1, batch, episodes, losses, extra)
                self.curve.append(row)
                if writer is not None:
                    for key, value in row.items():
                        if key not in ("iteration", "env_steps") and value is not None:
                            writer.add_scalar(key, value, row["env_steps"])
                if self.on_iteration is not None:
                    self.on_iteration(self, it + 1)
                bar.update(1)
                if self.progress and recent:
                    bar.set_postfix(
                        ret=f"{np.mean([e['return'] for e in recent]):.2f}", refresh=False
                    )
                if (it + 1) % self.cfg["save_interval"] == 0 and it + 1 < self.total_iterations:
                    self.save(self.out_dir / LAST, completed=False)
        except (KeyboardInterrupt, AmuledError) as stop:
            # Ctrl-C, or a belief backend that stayed down after its retries: keep the work.
            bar.close()
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

    def _curve_row(
        self, it: int, batch: int, episodes: list[dict], losses: dict, extra: dict
    ) -> dict[str, Any]:
        row: dict[str, Any] = {
            "iteration": it,
            "env_steps": it * batch,
            "wall_s": round(self.wall_offset, 4),
            "charts/lr": self.alg.learning_rate,
        }
        for key, value in losses.items():
            row[f"losses/{key}"] = (
                float(value) if value is not None and math.isfinite(value) else None
            )
        keys = sorted({k for e in episodes for k in e if k != "env_id"})
        row["charts/episodes"] = len(episodes)
        for key in keys:
            row[f"episode/{key}"] = _mean([e[key] for e in episodes if key in e])
        for key, value in extra.items():
            row[f"feedback/{key}"] = value
        return row

    def policy(self) -> torch.nn.Module:
        """Return the trained actor (an rsl-rl ``MLPModel``) in eval mode."""
        self.alg.eval_mode()
        return self.alg.get_policy()


def load_policy(checkpoint: Path, scenario: Scenario) -> torch.nn.Module:
    """Load the actor of a checkpoint for evaluation.

    Args:
        checkpoint: A checkpoint written by :class:`Trainer`.
        scenario: The scenario it was trained on (network shape).

    Returns:
        The actor in eval mode; call :func:`action_log_probs` on observations.

    Raises:
        CheckpointError: The file is missing or unreadable.

    """
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    state = read_checkpoint(checkpoint)
    infos = state.get("infos") or {}
    weights = state["actor_state_dict"]
    try:
        obs_dim = (
            infos.get("obs_dim") or next(v for k, v in weights.items() if "weight" in k).shape[1]
        )
        num_actions = infos.get("num_actions") or list(weights.values())[-1].shape[0]
        cfg = rsl_rl_config(scenario.ppo, num_steps_per_env=1)["actor"]
        cfg.pop("class_name")
        obs = TensorDict({OBS_GROUP: torch.zeros(1, obs_dim)}, batch_size=[1])
        actor = MLPModel(obs, {"actor": [OBS_GROUP]}, "actor", num_actions, **cfg)
        actor.load_state_dict(weights)
    except (AttributeError, IndexError, RuntimeError, StopIteration, TypeError) as error:
        raise CheckpointError(
            f"checkpoint {checkpoint}: its actor does not fit the scenario's network ({error}); "
            "evaluate it with the scenario it was trained on, or retrain it with --force"
        ) from error
    actor.eval()
    return actor
