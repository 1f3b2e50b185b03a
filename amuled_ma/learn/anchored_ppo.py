"""rsl-rl's PPO with a fine-tune's KL anchor, plugged in by ``cfg["algorithm"]["class_name"]``.

Unanchored (base training) it is rsl-rl's PPO with CleanRL's Adam and critic initialisation;
two CleanRL habits of the update (``finetune_moral.py``) are its options (`EpochShuffledStorage`,
`clip_jointly`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Generator
from itertools import chain
from typing import TYPE_CHECKING, Any, Literal

import torch
from rsl_rl.algorithms import PPO
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from amuled_ma.learn.anchors import EpisodeWindowKL, per_sample_kl
from amuled_ma.learn.distribution import orthogonal_init

if TYPE_CHECKING:
    from collections.abc import Iterable

    from rsl_rl.models import MLPModel
    from torch.utils.hooks import RemovableHandle

#: ``per_sample``: the paper's ``log pi(a|s) - log pi_base(a|s)``; ``window``: the authors'.
AnchorKind = Literal["per_sample", "window"]

#: ``per_network``: rsl-rl clips actor and critic apart; ``joint``: one norm (CleanRL).
GradClip = Literal["per_network", "joint"]


def adam(params: Iterable[torch.nn.Parameter], lr: float, eps: float) -> torch.optim.Optimizer:
    """Adam as CleanRL builds it, with torch's fused kernel where the device has one."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)
    except (RuntimeError, TypeError):  # pragma: no cover - a device without the kernel
        return torch.optim.Adam(params, lr=lr, eps=eps, foreach=True)


class EpochShuffledStorage(RolloutStorage):
    """rsl-rl's rollout storage whose mini-batches are re-partitioned in every epoch."""

    @classmethod
    def like(cls, storage: RolloutStorage) -> EpochShuffledStorage:
        """An empty storage of the same kind and shape as ``storage`` (the one rsl-rl built)."""
        return cls(
            storage.training_type,
            storage.num_envs,
            storage.num_transitions_per_env,
            storage.observations[0],  # one step of every observation group: [num_envs, ...]
            storage.actions_shape,
            storage.device,
        )

    def mini_batch_generator(
        self, num_mini_batches: int, num_epochs: int = 8
    ) -> Generator[RolloutStorage.Batch, None, None]:
        """Yield ``num_epochs`` epochs of mini-batches, each epoch a new partition."""
        for _ in range(num_epochs):
            yield from super().mini_batch_generator(num_mini_batches, 1)


def clip_jointly(optimizer: torch.optim.Optimizer, max_norm: float) -> RemovableHandle:
    """Clip all of ``optimizer``'s gradients as one vector before each step; the hook's handle.

    Raises ValueError: ``max_norm`` is not a positive finite number.
    """
    max_norm = float(max_norm)
    if not 0 < max_norm < float("inf"):
        raise ValueError(f"max_norm: expected a positive finite number, got {max_norm!r}")

    def hook(opt: torch.optim.Optimizer, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        params = [p for g in opt.param_groups for p in g["params"] if p.grad is not None]
        if params:
            torch.nn.utils.clip_grad_norm_(params, max_norm)

    return optimizer.register_step_pre_hook(hook)


class AnchoredPPO(PPO):
    """PPO anchored to a frozen base policy by ``lambda_kl`` times a KL term in the reward.

    ``reshuffle_each_epoch`` draws a new mini-batch partition every epoch and
    ``bootstrap_time_outs`` False treats a truncation as a termination (both CleanRL's);
    ``kwargs`` are rsl-rl's ``PPO`` arguments.
    """

    def __init__(
        self,
        actor: MLPModel,
        critic: MLPModel,
        storage: RolloutStorage,
        *,
        lambda_kl: float = 0.0,
        anchor: AnchorKind = "per_sample",
        adam_eps: float = 1e-5,
        grad_clip: GradClip = "per_network",
        reshuffle_each_epoch: bool = False,
        bootstrap_time_outs: bool = True,
        **kwargs: Any,
    ) -> None:
        joint_norm = None
        if grad_clip == "joint":
            joint_norm = float(kwargs.get("max_grad_norm", 1.0))  # rsl-rl's default: 1.0
            kwargs["max_grad_norm"] = math.inf  # rsl-rl's per-network clips: a factor of 1
        if reshuffle_each_epoch:
            storage = EpochShuffledStorage.like(storage)
        super().__init__(actor, critic, storage, **kwargs)
        # CleanRL's critic initialisation (the actor's: the distribution's init_mlp_weights)
        orthogonal_init(self.critic, last_std=1.0)
        self.optimizer = adam(
            chain(self.actor.parameters(), self.critic.parameters()),
            lr=self.learning_rate,
            eps=adam_eps,
        )
        self.grad_clip: GradClip = grad_clip
        self.joint_max_grad_norm = joint_norm
        if joint_norm is not None:
            clip_jointly(self.optimizer, joint_norm)
        self.bootstrap_time_outs = bool(bootstrap_time_outs)
        #: A float; a population's subclass holds one weight per row (a tensor).
        self.lambda_kl: float | torch.Tensor = float(lambda_kl)
        self.anchor_kind: AnchorKind = anchor
        self.base_actor: Any | None = None
        self.window: EpisodeWindowKL | None = None
        self.last_losses: dict[str, float] = {}
        self.member_losses: list[dict[str, float]] = [{}]
        self._anchor: torch.Tensor | None = None
        #: Members (one here; a population's subclass has more) and copies of each.
        self.population, self.copies = 1, self.storage.num_envs
        #: ``[2, P]`` sums of each member's feedback and anchor, one per step of the rollout
        self.step_sums: list[torch.Tensor] = []

    def anchor_to(self, base_actor: torch.nn.Module) -> None:
        """Anchor the policy to a frozen, eval-mode copy of ``base_actor`` (a fine-tune's base)."""
        base = copy.deepcopy(base_actor)
        base.eval()
        for p in base.parameters():
            p.requires_grad_(False)
        self.base_actor = base
        if self.anchor_kind == "window":
            self.window = EpisodeWindowKL(
                self.storage.num_envs, self.storage.num_transitions_per_env
            )

    def set_learning_rate(self, lr: float) -> None:
        """Set the learning rate of the optimiser (the trainer's schedule)."""
        self.learning_rate = float(lr)
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate

    def act(self, obs: TensorDict) -> torch.Tensor:
        """rsl-rl's ``act``; when anchored, also the anchor of the sampled actions."""
        actions = super().act(obs)
        if self.base_actor is not None:
            # our categorical head keeps the log-probabilities of its last forward pass,
            # deterministic or not, so the base policy is read without a sample
            self.base_actor(obs)
            logp_base = self.base_actor.get_output_log_prob(actions).reshape(-1)
            logp = self.transition.actions_log_prob.reshape(-1)
            self._anchor = self.anchor_of(logp, logp_base)
        return actions

    def anchor_of(self, logp: torch.Tensor, logp_base: torch.Tensor) -> torch.Tensor:
        """The recipe's anchor ``[N]`` of this step from the taken actions' log-probabilities."""
        if self.window is not None:
            return self.window.step(logp, logp_base)
        return per_sample_kl(logp, logp_base)

    def process_env_step(
        self,
        obs: TensorDict,
        rewards: torch.Tensor,
        dones: torch.Tensor,
        extras: dict[str, Any],
    ) -> None:
        """Subtract ``lambda_KL * anchor`` from the MDP's reward, then rsl-rl's step.

        Without ``bootstrap_time_outs`` rsl-rl is not shown ``extras["time_outs"]``.
        """
        if not self.bootstrap_time_outs and "time_outs" in extras:
            extras = {k: v for k, v in extras.items() if k != "time_outs"}
        anchor = self._anchor
        if anchor is not None:
            rewards = rewards - self.lambda_kl * anchor
            feedback = extras.get("feedback")
            if feedback is None:
                feedback = torch.zeros_like(anchor)
            both = torch.stack((feedback.to(anchor.device, anchor.dtype), anchor))
            self.step_sums.append(both.reshape(2, self.population, -1).sum(2))
            if self.window is not None:
                self.window.end_episodes(dones)
            self._anchor = None
        super().process_env_step(obs, rewards, dones, extras)

    def compute_returns(self, obs: TensorDict) -> None:
        """rsl-rl's returns; then the authors' windows start afresh for the next rollout."""
        super().compute_returns(obs)
        if self.window is not None:
            self.window.start_iteration()

    def update(self) -> dict[str, float]:
        """rsl-rl's update; its losses are also kept in ``last_losses`` and ``member_losses``."""
        self.last_losses = super().update()
        self.member_losses = [self.last_losses]
        return self.last_losses

    def failed_members(self) -> list[int]:
        """``[0]`` when the last update made a weight not finite (a NaN or inf), else ``[]``."""
        # a NaN or inf anywhere makes its parameter's sum not finite: one reduction each
        sums = torch.stack([p.sum() for p in (*self.actor.parameters(), *self.critic.parameters())])
        return [] if bool(torch.isfinite(sums).all()) else [0]

    def member_rollout_stats(self) -> list[dict[str, float]]:
        """Each member's mean ``feedback_reward`` and ``kl`` per step since the last call.

        ``{}`` for each member when no anchored step was taken.
        """
        if not self.step_sums:
            return [{} for _ in range(self.population)]
        # [steps, 2, P] float32 sums of each step, added in float64
        sums = torch.stack(self.step_sums).to("cpu", torch.float64).sum(0)
        count = len(self.step_sums) * self.copies
        self.step_sums = []
        return [
            {"feedback_reward": fb / count, "kl": kl / count}
            for fb, kl in zip(sums[0].tolist(), sums[1].tolist(), strict=True)
        ]
