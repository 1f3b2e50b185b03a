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
"""

from __future__ import annotations

import copy
from itertools import chain
from typing import Any, Literal

import torch
from rsl_rl.algorithms import PPO
from tensordict import TensorDict

from amuled_ma.learn.anchors import EpisodeWindowKL, per_sample_kl
from amuled_ma.learn.distribution import orthogonal_init

#: ``per_sample``: the paper's ``log pi(a|s) - log pi_base(a|s)`` of each step;
#: ``window``: the authors' mean over the episode so far (:class:`EpisodeWindowKL`).
AnchorKind = Literal["per_sample", "window"]


def adam(params: Any, lr: float, eps: float) -> torch.optim.Optimizer:
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
        **kwargs: rsl-rl's :class:`~rsl_rl.algorithms.PPO` arguments.

    """

    def __init__(
        self,
        actor: Any,
        critic: Any,
        storage: Any,
        *,
        lambda_kl: float = 0.0,
        anchor: AnchorKind = "per_sample",
        adam_eps: float = 1e-5,
        **kwargs: Any,
    ) -> None:
        super().__init__(actor, critic, storage, **kwargs)
        if anchor not in ("per_sample", "window"):
            raise ValueError(f"anchor: expected 'per_sample' or 'window', got {anchor!r}")
        # CleanRL's initialisation of the critic (rsl-rl's actor gets it from the
        # distribution's init_mlp_weights) and CleanRL's Adam.
        orthogonal_init(self.critic, last_std=1.0)
        self.optimizer = adam(
            chain(self.actor.parameters(), self.critic.parameters()),
            lr=self.learning_rate,
            eps=adam_eps,
        )
        self.lambda_kl = float(lambda_kl)
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
            if self.window is not None:
                self._anchor = self.window.step(logp, logp_base)
            else:
                self._anchor = per_sample_kl(logp, logp_base)
        return actions

    def process_env_step(
        self,
        obs: TensorDict,
        rewards: torch.Tensor,
        dones: torch.Tensor,
        extras: dict[str, Any],
    ) -> None:
        """Subtract ``lambda_KL * anchor`` from the MDP's reward, then rsl-rl's step."""
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
