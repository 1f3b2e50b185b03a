"""A lean PPO update with exactly the numbers of rsl-rl's :meth:`PPO.update`.

rsl-rl's update is written for every feature it supports (recurrent models, RND,
symmetry, multi-GPU, mixed precision, an adaptive learning rate); with our small
feed-forward categorical actor-critic on CPU its per-mini-batch Python overhead
(TensorDict indexing, module wrappers, the generic gradient clipping, three
``.item()`` calls per mini-batch) costs more than the arithmetic. :func:`ppo_update`
does the same operations in the same order on the same tensors, so parameters,
optimiser state, losses and the torch random stream (the actor still draws its
discarded per-mini-batch sample, as rsl-rl's does) come out bit-identical; it falls
back to ``alg.update()`` for any configuration it does not cover.
"""

from __future__ import annotations

from typing import Any

import torch

from amuled_ma.learn.distribution import CategoricalDistribution


def _plain_mlp(model: Any) -> bool:
    """Whether ``model`` is an rsl-rl MLPModel reading one observation group, unnormalised."""
    return (
        not getattr(model, "is_recurrent", True)
        and not getattr(model, "obs_normalization", True)
        and isinstance(getattr(model, "obs_normalizer", None), torch.nn.Identity)
        and len(getattr(model, "obs_groups", ())) == 1
        and hasattr(model, "mlp")
    )


def supports(alg: Any) -> bool:
    """Return whether :func:`ppo_update` reproduces ``alg.update()`` for this algorithm.

    Args:
        alg: An rsl-rl :class:`~rsl_rl.algorithms.PPO` instance.

    """
    return (
        type(alg).__name__ == "PPO"
        and not alg.rnd
        and not alg.symmetry
        and not getattr(alg, "is_multi_gpu", False)
        and not getattr(alg, "use_mixed_precision", False)
        and not (alg.desired_kl is not None and alg.schedule == "adaptive")
        and getattr(alg.storage, "training_type", None) == "rl"
        and _plain_mlp(alg.actor)
        and _plain_mlp(alg.critic)
        and isinstance(getattr(alg.actor, "distribution", None), CategoricalDistribution)
        and getattr(alg.critic, "distribution", None) is None
        and alg.actor.obs_groups == alg.critic.obs_groups
        and list(alg.storage.observations.keys()) == list(alg.actor.obs_groups)
    )


def mlp_forward(mlp: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``mlp(x)`` for an rsl-rl MLP of Linear and Tanh layers, without the module wrappers.

    ``F.linear`` and ``torch.tanh`` are exactly what ``nn.Linear`` and ``nn.Tanh`` call;
    any other layer (or a hook on one) goes through the module itself.
    """
    if mlp._forward_hooks or mlp._forward_pre_hooks:
        return mlp(x)
    for layer in mlp:
        kind = type(layer)
        if kind is torch.nn.Linear and not (layer._forward_hooks or layer._forward_pre_hooks):
            x = torch.nn.functional.linear(x, layer.weight, layer.bias)
        elif kind is torch.nn.Tanh and not (layer._forward_hooks or layer._forward_pre_hooks):
            x = torch.tanh(x)
        else:
            x = layer(x)
    return x


def _clip_grad_norm(params: list[torch.Tensor], max_norm: float) -> None:
    """``torch.nn.utils.clip_grad_norm_`` (2-norm, foreach, one CPU dtype), minus its wrappers."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return
    norms = torch._foreach_norm(grads, 2.0)
    total = torch.linalg.vector_norm(torch.stack(norms), 2.0)
    coef = torch.clamp(float(max_norm) / (total + 1e-6), max=1.0)
    torch._foreach_mul_(grads, coef)


def ppo_update(alg: Any) -> dict[str, float]:
    """Run rsl-rl's PPO update (epochs x mini-batches) and return its mean losses.

    Args:
        alg: An rsl-rl :class:`~rsl_rl.algorithms.PPO` instance whose storage holds a
            finished rollout (after ``compute_returns``).

    Returns:
        ``{"value", "surrogate", "entropy"}`` as ``alg.update()`` returns them.

    """
    if not supports(alg):
        return alg.update()
    actor, critic, st = alg.actor, alg.critic, alg.storage
    dist: CategoricalDistribution = actor.distribution
    group = actor.obs_groups[0]
    critic_group = critic.obs_groups[0]
    num_mb, num_epochs = alg.num_mini_batches, alg.num_learning_epochs
    batch_size = st.num_envs * st.num_transitions_per_env
    mb_size = batch_size // num_mb
    indices = torch.randperm(num_mb * mb_size, requires_grad=False, device=st.device)
    obs_td = st.observations.flatten(0, 1)
    obs_actor = obs_td[group]
    obs_critic = obs_td[critic_group]
    actions = st.actions.flatten(0, 1)
    values_old = st.values.flatten(0, 1)
    returns = st.returns.flatten(0, 1)
    old_logp = st.actions_log_prob.flatten(0, 1)
    advantages = st.advantages.flatten(0, 1)
    actor_params = list(actor.parameters())
    critic_params = list(critic.parameters())
    clip, vcoef, ecoef = alg.clip_param, alg.value_loss_coef, alg.entropy_coef
    per_mb = alg.normalize_advantage_per_mini_batch
    losses: list[torch.Tensor] = []
    for _ in range(num_epochs):
        for i in range(num_mb):
            idx = indices[i * mb_size : (i + 1) * mb_size]
            adv = advantages[idx]
            if per_mb:
                with torch.no_grad():
                    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            b_values = values_old[idx]
            b_returns = returns[idx]
            # actor: logits -> log-softmax; rsl-rl draws a (discarded) sample here
            dist.update(mlp_forward(actor.mlp, obs_actor[idx]))
            dist.sample()
            log_probs = dist.log_prob(actions[idx])
            values = mlp_forward(critic.mlp, obs_critic[idx])
            entropy = dist.entropy
            ratio = torch.exp(log_probs - torch.squeeze(old_logp[idx]))
            surrogate = -torch.squeeze(adv) * ratio
            surrogate_clipped = -torch.squeeze(adv) * torch.clamp(ratio, 1.0 - clip, 1.0 + clip)
            surrogate_loss = torch.max(surrogate, surrogate_clipped).mean()
            if alg.use_clipped_value_loss:
                value_clipped = b_values + (values - b_values).clamp(-clip, clip)
                value_losses = (values - b_returns).pow(2)
                value_losses_clipped = (value_clipped - b_returns).pow(2)
                value_loss = torch.max(value_losses, value_losses_clipped).mean()
            else:
                value_loss = (b_returns - values).pow(2).mean()
            entropy_mean = entropy.mean()
            loss = surrogate_loss + vcoef * value_loss - ecoef * entropy_mean
            alg.optimizer.zero_grad()
            loss.backward()
            _clip_grad_norm(actor_params, alg.max_grad_norm)
            _clip_grad_norm(critic_params, alg.max_grad_norm)
            alg.optimizer.step()
            losses.append(torch.stack([value_loss, surrogate_loss, entropy_mean]).detach())
    obs_flat = st.observations.flatten(0, 1)
    actor.update_normalization(obs_flat)
    critic.update_normalization(obs_flat)
    # rsl-rl adds Python floats one mini-batch at a time; do the same, in the same order
    sums = [0, 0, 0]
    for row in torch.stack(losses).tolist() if losses else []:
        for j in range(3):
            sums[j] += row[j]
    n = num_epochs * num_mb
    st.clear()
    return {"value": sums[0] / n, "surrogate": sums[1] / n, "entropy": sums[2] / n}


def act(alg: Any, state: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """rsl-rl's ``PPO.act`` on a plain observation tensor, without the transition object.

    Same operations in the same order (actor logits, sample, critic value, log-probability),
    so the same actions and the same random draws. Call under ``torch.inference_mode()``.

    Args:
        alg: An rsl-rl PPO instance for which :func:`supports` holds.
        state: Observations ``[N, obs_dim]`` (the single observation group).

    Returns:
        ``(actions, values, actions_log_prob, log_probs)``: one-hot actions ``[N, A]``,
        values ``[N, 1]``, log-probabilities of the actions ``[N]`` and of every action
        ``[N, A]`` (the distribution parameters rsl-rl stores).

    """
    dist: CategoricalDistribution = alg.actor.distribution
    dist.update(mlp_forward(alg.actor.mlp, state))
    actions = dist.sample()
    values = mlp_forward(alg.critic.mlp, state)
    return actions, values, dist.log_prob(actions), dist.logits


def record(
    alg: Any,
    state: torch.Tensor,
    actions: torch.Tensor,
    values: torch.Tensor,
    actions_log_prob: torch.Tensor,
    log_probs: torch.Tensor,
    rewards: torch.Tensor,
    dones: torch.Tensor,
    time_outs: torch.Tensor,
) -> None:
    """rsl-rl's ``PPO.process_env_step`` plus ``RolloutStorage.add_transition``, direct.

    The reward is bootstrapped on time-outs (``r + gamma * V(s) * time_out``) exactly as
    rsl-rl does, and every tensor is copied into the same storage slot.

    Args:
        alg: An rsl-rl PPO instance for which :func:`supports` holds.
        state: Observations the actions were taken in ``[N, obs_dim]``.
        actions: One-hot actions ``[N, A]`` (from :func:`act`).
        values: Critic values ``[N, 1]``.
        actions_log_prob: ``[N]``.
        log_probs: ``[N, A]``.
        rewards: ``[N]``.
        dones: ``[N]`` (float, terminated or truncated).
        time_outs: ``[N]`` (float, truncated and not terminated).

    """
    st = alg.storage
    if st.step >= st.num_transitions_per_env:
        raise OverflowError("rollout buffer overflow: call clear() before adding transitions")
    rewards = rewards.clone()
    rewards += alg.gamma * torch.squeeze(values * time_outs.unsqueeze(1).to(alg.device), 1)
    step = st.step
    st.observations[alg.actor.obs_groups[0]][step].copy_(state)
    st.actions[step].copy_(actions)
    st.rewards[step].copy_(rewards.view(-1, 1))
    st.dones[step].copy_(dones.view(-1, 1))
    st.values[step].copy_(values)
    st.actions_log_prob[step].copy_(actions_log_prob.view(-1, 1))
    if st.distribution_params is None:
        st.distribution_params = (
            torch.zeros(st.num_transitions_per_env, *log_probs.shape, device=st.device),
        )
    st.distribution_params[0][step].copy_(log_probs)
    st.step += 1
