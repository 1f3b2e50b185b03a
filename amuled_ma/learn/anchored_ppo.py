"""rsl-rl's PPO with the KL anchor of a fine-tune, plugged in by ``class_name``.

rsl-rl resolves ``cfg["algorithm"]["class_name"]`` (a ``"module:Class"`` string) and
builds the algorithm with :meth:`~rsl_rl.algorithms.PPO.construct_algorithm`, passing the
other keys of ``cfg["algorithm"]`` to the constructor; :class:`AnchoredPPO` is such a
class. It subclasses :class:`~rsl_rl.algorithms.PPO` and overrides three of its public
steps, each calling rsl-rl's own method:

- :meth:`act` also evaluates the frozen base policy on the same observations and keeps
  the anchor of the step (the recipe's KL term, :mod:`amuled_ma.learn.anchors`);
- :meth:`process_env_step` subtracts ``lambda_KL * anchor`` from the environment's reward
  (the deliberation MDP's actor reward, :func:`~amuled_ma.deliberation.mdp.actor_reward`)
  before rsl-rl records the transition;
- :meth:`compute_returns` closes the rollout (the authors' recipe empties its windows).

Without a base policy (:meth:`anchor_to` never called: base training) it is rsl-rl's PPO
with CleanRL's Adam (``eps = 1e-5``) and critic initialisation. Everything else (storage,
returns, the update, checkpoints) is rsl-rl's, unchanged.

Three options (off by default) switch an rsl-rl habit to the CleanRL loop the AMULED
authors fine-tuned with (:mod:`amuled_ma.learn.ppo_options`): ``grad_clip = "joint"`` (one
gradient norm over actor and critic), ``reshuffle_each_epoch`` (a new mini-batch partition
in every epoch) and ``bootstrap_time_outs = False`` (no value bootstrap at a truncation).
"""

from __future__ import annotations

import copy
import math
from itertools import chain
from typing import TYPE_CHECKING, Any, Literal

import torch
from rsl_rl.algorithms import PPO
from tensordict import TensorDict

from amuled_ma.learn.anchors import EpisodeWindowKL, per_sample_kl
from amuled_ma.learn.distribution import orthogonal_init
from amuled_ma.learn.ppo_options import EpochShuffledStorage, clip_jointly

if TYPE_CHECKING:
    from collections.abc import Iterable

    from rsl_rl.models import MLPModel
    from rsl_rl.storage import RolloutStorage

#: ``per_sample``: the paper's ``log pi(a|s) - log pi_base(a|s)`` of each step;
#: ``window``: the authors' mean over the episode so far (:class:`EpisodeWindowKL`).
AnchorKind = Literal["per_sample", "window"]

#: ``per_network``: rsl-rl clips the actor's and the critic's gradient norms apart;
#: ``joint``: one norm over both (CleanRL, :func:`~amuled_ma.learn.ppo_options.clip_jointly`).
GradClip = Literal["per_network", "joint"]


def adam(params: Iterable[torch.nn.Parameter], lr: float, eps: float) -> torch.optim.Optimizer:
    """Adam as CleanRL builds it, with torch's fused kernel where the device has one.

    On CPU with small networks the per-parameter loop of the default implementation is a
    large part of an update; ``fused=True`` is torch's public option for one kernel.
    """
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)
    except (RuntimeError, TypeError):  # pragma: no cover - a device without the kernel
        return torch.optim.Adam(params, lr=lr, eps=eps, foreach=True)


class AnchoredPPO(PPO):
    """PPO anchored to a frozen base policy by a KL term in the reward.

    Args:
        actor: rsl-rl actor model (categorical head, :mod:`amuled_ma.learn.distribution`).
        critic: rsl-rl critic model.
        storage: rsl-rl rollout storage.
        lambda_kl: Weight of the anchor in the reward.
        anchor: Which KL term (:data:`AnchorKind`).
        adam_eps: Adam's ``eps`` (CleanRL: ``1e-5``; torch's default is ``1e-8``).
        grad_clip: ``per_network`` (rsl-rl) or ``joint`` (CleanRL: ``max_grad_norm`` bounds
            the norm of actor and critic gradients together; rsl-rl's own two clips are
            handed ``inf`` and scale by exactly 1).
        reshuffle_each_epoch: Draw a new mini-batch partition in every epoch (CleanRL)
            instead of one per update (rsl-rl).
        bootstrap_time_outs: Add ``gamma * V(s)`` to the reward of a step that ends by the
            time limit (rsl-rl); False treats a truncation as a termination (CleanRL).
        **kwargs: rsl-rl's :class:`~rsl_rl.algorithms.PPO` arguments.

    Raises:
        ValueError: ``anchor`` or ``grad_clip`` is not one of its choices.

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
        if anchor not in ("per_sample", "window"):
            raise ValueError(f"anchor: expected 'per_sample' or 'window', got {anchor!r}")
        if grad_clip not in ("per_network", "joint"):
            raise ValueError(f"grad_clip: expected 'per_network' or 'joint', got {grad_clip!r}")
        joint_norm = None
        if grad_clip == "joint":
            joint_norm = float(kwargs.get("max_grad_norm", 1.0))  # rsl-rl's default: 1.0
            kwargs["max_grad_norm"] = math.inf  # rsl-rl's per-network clips: a factor of 1
        if reshuffle_each_epoch:
            storage = EpochShuffledStorage.like(storage)
        super().__init__(actor, critic, storage, **kwargs)
        # CleanRL's initialisation of the critic (rsl-rl's actor gets it from the
        # distribution's init_mlp_weights) and CleanRL's Adam.
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
        self._anchor: torch.Tensor | None = None
        self._stats = torch.zeros(3, dtype=torch.float64)  # feedback sum, anchor sum, count

    # ----------------------------------------------------------------- anchoring
    def anchor_to(self, base_actor: torch.nn.Module) -> None:
        """Anchor the policy to a frozen copy of ``base_actor`` (a fine-tune's base).

        Args:
            base_actor: An actor model of the same shape as :attr:`actor`, with the base
                policy's weights; it is copied, frozen and put in eval mode.

        """
        base = copy.deepcopy(base_actor)
        base.eval()
        for p in base.parameters():
            p.requires_grad_(False)
        self.base_actor = base
        if self.anchor_kind == "window":
            self.window = EpisodeWindowKL(
                self.storage.num_envs, self.storage.num_transitions_per_env
            )

    @property
    def anchored(self) -> bool:
        """Whether a base policy anchors this PPO (a fine-tune)."""
        return self.base_actor is not None

    def set_learning_rate(self, lr: float) -> None:
        """Set the learning rate of the optimiser (the trainer's schedule)."""
        self.learning_rate = float(lr)
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate

    # ----------------------------------------------------------------- rsl-rl steps
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
        """The recipe's anchor of this step, from the taken actions' log-probabilities.

        Args:
            logp: ``[N]`` log-probabilities under the fine-tuned policy.
            logp_base: ``[N]`` the same actions under the base policy.

        Returns:
            ``[N]``: the authors' window KL (``anchor = "window"``) or the per-sample KL.

        """
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

        Without ``bootstrap_time_outs`` rsl-rl is not shown the ``time_outs`` of
        ``extras``: a truncated step is then closed like a terminated one (CleanRL).
        """
        if not self.bootstrap_time_outs and "time_outs" in extras:
            extras = {k: v for k, v in extras.items() if k != "time_outs"}
        anchor = self._anchor
        if anchor is not None:
            rewards = rewards - self.lambda_kl * anchor
            feedback = extras.get("feedback")
            if feedback is not None:
                self._stats[0] += float(feedback.sum())
            self._stats[1] += float(anchor.sum())
            self._stats[2] += anchor.numel()
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
        """rsl-rl's update; the losses are also kept in :attr:`last_losses`."""
        self.last_losses = super().update()
        return self.last_losses

    def rollout_stats(self) -> dict[str, float]:
        """Mean feedback ``f(B)[a]`` and anchor per step since the last call (fine-tunes).

        Returns:
            ``{"feedback_reward": ..., "kl": ...}``, or ``{}`` when nothing was anchored.

        """
        total_fb, total_kl, count = self._stats.tolist()
        self._stats.zero_()
        if not count:
            return {}
        return {"feedback_reward": total_fb / count, "kl": total_kl / count}
