"""The shape of one training job: copies, rollout, iterations, learning rate, rsl-rl config."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from amuled_ma.errors import ScenarioError
from amuled_ma.learn.config import planned_iterations, rsl_rl_config
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import BaseConfig, FinetuneConfig, PPOConfig


@dataclass(frozen=True)
class JobShape:
    """What a job's scenario and variant decide about its training loop.

    ``task_weight`` weighs the task reward in the actor's reward; ``cfg`` is rsl-rl's config
    (pass a deep copy).
    """

    finetuning: bool
    num_envs: int
    steps_per_env: int
    total_iterations: int
    learning_rate: float
    anneal: bool
    shaping_coef: float
    task_weight: float
    cfg: dict[str, Any]

    @property
    def batch(self) -> int:
        """Transitions per iteration (``num_envs x steps_per_env``)."""
        return self.num_envs * self.steps_per_env

    def lr_at(self, iteration: int) -> float:
        """The learning rate of ``iteration`` (0-based): constant, or linearly annealed."""
        if self.anneal:
            return self.learning_rate * (1.0 - iteration / self.total_iterations)
        return self.learning_rate


def job_shape(
    ppo: PPOConfig,
    base: BaseConfig,
    finetune: FinetuneConfig,
    variant: Variant,
    iterations: int | None = None,
    *,
    where: str,
) -> JobShape:
    """The shape of training ``variant`` by the ``[ppo]``, ``[base]`` and ``[finetune]`` sections.

    ``iterations`` overrides the planned number; ``where`` names the scenario in messages.

    Raises:
        ScenarioError: Per-mini-batch advantage normalisation of 1-transition mini-batches.
    """
    run: BaseConfig | FinetuneConfig = base
    lr, anneal, task_weight, section = ppo.learning_rate, ppo.anneal_lr, 1.0, "base"
    own: dict[str, Any] = {}
    if variant.finetuning:
        run, section, task_weight = finetune, "finetune", finetune.env_reward_coef
        lr, anneal = finetune.learning_rate, finetune.anneal_lr
        own = {
            "learning_rate": finetune.learning_rate,
            "num_learning_epochs": finetune.num_learning_epochs,
            "lambda_kl": finetune.lambda_kl,
            "anchor": "window" if finetune.recipe == "authors" else "per_sample",
        }
    num_envs, steps = run.num_envs, run.num_steps_per_env
    total = planned_iterations(run) if iterations is None else iterations
    cfg = rsl_rl_config(
        ppo,
        num_steps_per_env=steps,
        save_interval=run.save_interval,
        grad_clip=run.grad_clip,
        reshuffle_each_epoch=run.reshuffle_each_epoch,
        bootstrap_time_outs=run.bootstrap_time_outs,
        **own,
    )
    shaping = base.shaping_coef if variant.kind == "shaped" else 0.0
    minibatch = num_envs * steps // ppo.num_mini_batches
    if ppo.normalize_advantage_per_mini_batch and minibatch < 2:
        raise ScenarioError(
            f"{where}: [{section}] num_envs x num_steps_per_env = "
            f"{num_envs * steps} transitions split into "
            f"[ppo] num_mini_batches = {ppo.num_mini_batches} gives mini-batches of "
            f"{minibatch}; per-mini-batch advantage normalisation needs at least 2 "
            "(raise num_envs or num_steps_per_env)"
        )
    return JobShape(
        finetuning=variant.finetuning,
        num_envs=num_envs,
        steps_per_env=steps,
        total_iterations=total,
        learning_rate=lr,
        anneal=anneal,
        shaping_coef=shaping,
        task_weight=task_weight,
        cfg=cfg,
    )
