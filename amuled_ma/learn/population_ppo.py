"""rsl-rl's PPO for a population: P members in one update, each updated as it would be alone.

Each step of rsl-rl's that would mix the members is made per member at a public extension
point (docs/learning.md, "Population training"); Adam is elementwise, so one Adam over the
stacked parameters is each member's Adam.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Sequence
from typing import TYPE_CHECKING, Any

import torch
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from amuled_ma.learn.anchored_ppo import AnchoredPPO
from amuled_ma.learn.anchors import per_sample_kl
from amuled_ma.learn.population_models import MemberStreams

if TYPE_CHECKING:
    from amuled_ma.learn.population_models import PopulationMLPModel

#: Loss keys rsl-rl's update returns, in the order kept per member.
LOSS_KEYS = ("value", "surrogate", "entropy")


class PopulationStorage(RolloutStorage):
    """rsl-rl's rollout storage (``like``, of ``P x E`` copies) with per-member mini-batches.

    ``per_mini_batch`` normalises advantages per member and mini-batch (else per rollout).
    """

    def __init__(
        self,
        like: RolloutStorage,
        population: int,
        streams: MemberStreams,
        *,
        per_mini_batch: bool,
        reshuffle_each_epoch: bool = False,
    ) -> None:
        super().__init__(
            like.training_type,
            like.num_envs,
            like.num_transitions_per_env,
            like.observations[0],  # one step of every observation group: [num_envs, ...]
            like.actions_shape,
            like.device,
        )
        self.population = int(population)
        self.copies = self.num_envs // self.population
        self.streams = streams
        self.per_mini_batch = bool(per_mini_batch)
        self.reshuffle_each_epoch = bool(reshuffle_each_epoch)
        #: The mini-batch last yielded (read by the optimiser's hook for per-member losses).
        self.last_batch: RolloutStorage.Batch | None = None

    def member_rows(self, used: int) -> torch.Tensor:
        """``[P, used]`` flat storage rows: each member's own permutation of its transitions.

        Member ``p``'s lone row ``t * E + e`` is the population's ``t * (P * E) + p * E + e``.
        """
        local = self.streams.permutations(used, torch.device(self.device))
        offsets = torch.arange(self.population, device=local.device).unsqueeze(1) * self.copies
        return (local // self.copies) * self.num_envs + offsets + local % self.copies

    def mini_batch_generator(
        self, num_mini_batches: int, num_epochs: int = 8
    ) -> Generator[RolloutStorage.Batch, None, None]:
        """Yield each epoch's mini-batches: every member's ``k``-th, member-major."""
        size = self.copies * self.num_transitions_per_env // num_mini_batches
        used = num_mini_batches * size
        observations = self.observations.flatten(0, 1)
        actions = self.actions.flatten(0, 1)
        values = self.values.flatten(0, 1)
        returns = self.returns.flatten(0, 1)
        old_log_prob = self.actions_log_prob.flatten(0, 1)
        old_params = tuple(p.flatten(0, 1) for p in self.distribution_params)
        advantages = returns - values  # rsl-rl's raw advantages, before its normalisation
        if not self.per_mini_batch:
            advantages = self._normalised_per_member_rollout(advantages)
        rows = None
        for _ in range(num_epochs):
            if rows is None or self.reshuffle_each_epoch:
                rows = self.member_rows(used)
            for i in range(num_mini_batches):
                index = rows[:, i * size : (i + 1) * size].reshape(-1)
                batch_adv = advantages[index]
                if self.per_mini_batch:
                    batch_adv = _normalised_rows(batch_adv.reshape(self.population, -1))
                    batch_adv = batch_adv.reshape(-1, 1)
                self.last_batch = RolloutStorage.Batch(
                    observations=observations[index],
                    actions=actions[index],
                    values=values[index],
                    advantages=batch_adv,
                    returns=returns[index],
                    old_actions_log_prob=old_log_prob[index],
                    old_distribution_params=tuple(p[index] for p in old_params),
                )
                yield self.last_batch

    def _normalised_per_member_rollout(self, advantages: torch.Tensor) -> torch.Tensor:
        """rsl-rl's rollout-wide normalisation, over each member's own transitions."""
        per_step = advantages.reshape(self.num_transitions_per_env, self.population, -1)
        members = per_step.transpose(0, 1).reshape(self.population, -1)
        normalised = _normalised_rows(members)
        shaped = normalised.reshape(self.population, self.num_transitions_per_env, -1)
        return shaped.transpose(0, 1).reshape(-1, 1)


def _normalised_rows(x: torch.Tensor) -> torch.Tensor:
    """``(x - mean) / (std + 1e-8)`` of each row (rsl-rl's formula, unbiased std)."""
    return (x - x.mean(dim=1, keepdim=True)) / (x.std(dim=1, keepdim=True) + 1e-8)


class PopulationPPO(AnchoredPPO):
    """rsl-rl's PPO (anchored) over a population, each member updated as it is alone.

    ``lambda_kl`` and ``anchor`` hold one value per member; ``kwargs`` are `AnchoredPPO`'s.
    """

    def __init__(
        self,
        actor: PopulationMLPModel,
        critic: PopulationMLPModel,
        storage: RolloutStorage,
        *,
        population: int,
        lambda_kl: Sequence[float],
        anchor: Sequence[str],
        max_grad_norm: float = 1.0,
        grad_clip: str = "per_network",
        normalize_advantage_per_mini_batch: bool = False,
        reshuffle_each_epoch: bool = False,
        **kwargs: Any,
    ) -> None:
        population = int(population)
        super().__init__(
            actor,
            critic,
            storage,
            lambda_kl=0.0,
            anchor="window" if "window" in anchor else "per_sample",
            # rsl-rl's clips and normalisation span all members: off (a factor of exactly
            # 1, no normalisation); the hook and the storage do them per member
            max_grad_norm=math.inf,
            normalize_advantage_per_mini_batch=False,
            **kwargs,
        )
        self.population = population
        self.copies = storage.num_envs // population
        self.member_max_grad_norm = float(max_grad_norm)
        self.member_grad_clip = grad_clip
        self.streams = MemberStreams(population)
        self.actor.distribution.streams = self.streams
        self.storage = PopulationStorage(
            storage,
            population,
            self.streams,
            per_mini_batch=normalize_advantage_per_mini_batch,
            reshuffle_each_epoch=reshuffle_each_epoch,
        )
        device = torch.device(self.device)
        lambdas = torch.tensor([float(v) for v in lambda_kl], device=device)
        self.lambda_kl = lambdas.repeat_interleave(self.copies)
        self.window_rows = torch.tensor(
            [kind == "window" for kind in anchor], device=device
        ).repeat_interleave(self.copies)
        self.member_loss_sums = torch.zeros(population, len(LOSS_KEYS), dtype=torch.float64)
        self.member_losses: list[dict[str, float]] = [{} for _ in range(population)]
        #: members whose gradient was not finite in this update (their rows were zeroed)
        self.nonfinite = torch.zeros(population, dtype=torch.bool, device=device)
        for parameter in (*self.actor.parameters(), *self.critic.parameters()):
            parameter.register_hook(self.keep_members_finite)
        self.optimizer.register_step_pre_hook(self.before_step)

    def act(self, obs: TensorDict) -> torch.Tensor:
        """`AnchoredPPO`'s ``act``; a rollout's first step reserves its samples' uniforms."""
        if self.storage.step == 0:
            self.streams.reserve(
                self.copies,
                self.storage.num_transitions_per_env,
                torch.float32,
                torch.device(self.device),
            )
        return super().act(obs)

    def anchor_of(self, logp: torch.Tensor, logp_base: torch.Tensor) -> torch.Tensor:
        """Each copy's anchor by its member's recipe (window KL or per-sample KL)."""
        per_sample = per_sample_kl(logp, logp_base)
        if self.window is None:
            return per_sample
        return torch.where(self.window_rows, self.window.step(logp, logp_base), per_sample)

    def update(self) -> dict[str, float]:
        """rsl-rl's update (losses averaged over members); each member's in ``member_losses``."""
        self.member_loss_sums.zero_()
        self.nonfinite.zero_()
        losses = super().update()
        updates = self.num_learning_epochs * self.num_mini_batches
        self.member_losses = [
            dict(zip(LOSS_KEYS, (v / updates for v in row), strict=True))
            for row in self.member_loss_sums.tolist()
        ]
        return losses

    def keep_members_finite(self, grad: torch.Tensor) -> torch.Tensor:
        """A gradient hook: a member's non-finite rows become zeros, the member ``nonfinite``.

        rsl-rl's one norm over all members would spread one member's NaN to all.
        """
        if torch.isfinite(grad.sum()):  # the usual case, in one reduction (no copy)
            return grad
        rows = grad.reshape(self.population, -1)
        bad = ~torch.isfinite(rows).all(dim=1)
        self.nonfinite |= bad
        return torch.where(bad.unsqueeze(1), torch.zeros_like(rows), rows).reshape(grad.shape)

    def failed_members(self) -> list[int]:
        """Members whose gradient was not finite in the last update."""
        return [int(p) for p in torch.nonzero(self.nonfinite).flatten().tolist()]

    def before_step(
        self, optimizer: torch.optim.Optimizer, args: tuple[Any, ...], kwargs: dict[str, Any]
    ) -> None:
        """The optimiser's step pre-hook: each member's gradient times ``P``, clipped; its losses.

        rsl-rl's gradient is of the mean loss over ``P x B`` rows: times ``P``, each member's own.
        """
        with torch.no_grad():
            actor = [p.grad for p in self.actor.parameters() if p.grad is not None]
            critic = [p.grad for p in self.critic.parameters() if p.grad is not None]
            if self.member_grad_clip == "joint":
                self._clip_members(actor + critic)
            else:
                self._clip_members(actor)
                self._clip_members(critic)
            self._add_member_losses()

    def _clip_members(self, grads: list[torch.Tensor]) -> None:
        """Scale by ``P`` and clip each member's slice of ``grads`` to its own norm."""
        if not grads:
            return
        members = self.population
        # each member's 2-norm over all its gradients (its rows of the stacked tensors)
        rows = torch.cat([g.reshape(members, -1) for g in grads], dim=1)
        total = members * torch.linalg.vector_norm(rows, dim=1)
        scale = members * (self.member_max_grad_norm / (total + 1e-6)).clamp(max=1.0)
        for g in grads:
            g.mul_(scale.reshape(members, *([1] * (g.dim() - 1))))

    def _add_member_losses(self) -> None:
        """Each member's value, surrogate and entropy loss (rsl-rl's terms) on this mini-batch."""
        batch = self.storage.last_batch
        if batch is None or self.critic.last_output is None:
            return
        members = self.population
        log_prob = self.actor.get_output_log_prob(batch.actions)
        ratio = torch.exp(log_prob - torch.squeeze(batch.old_actions_log_prob))
        advantages = torch.squeeze(batch.advantages)
        clip = self.clip_param
        surrogate = torch.max(
            -advantages * ratio, -advantages * torch.clamp(ratio, 1.0 - clip, 1.0 + clip)
        )
        values = self.critic.last_output
        if self.use_clipped_value_loss:
            clipped = batch.values + (values - batch.values).clamp(-clip, clip)
            value = torch.max((values - batch.returns).pow(2), (clipped - batch.returns).pow(2))
        else:
            value = (batch.returns - values).pow(2)
        entropy = self.actor.output_entropy
        rows = torch.stack((value.reshape(-1), surrogate, entropy))
        terms = rows.reshape(len(LOSS_KEYS), members, -1).mean(2).T
        self.member_loss_sums += terms.to("cpu", torch.float64)
