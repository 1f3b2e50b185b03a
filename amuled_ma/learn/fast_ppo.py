"""A lean PPO update with exactly the numbers of rsl-rl's :meth:`PPO.update`.

rsl-rl's update is written for every feature it supports (recurrent models, RND,
symmetry, multi-GPU, mixed precision, an adaptive learning rate); with our small
feed-forward categorical actor-critic on CPU its per-mini-batch Python overhead
(TensorDict indexing, module wrappers, the generic gradient clipping, three
``.item()`` calls per mini-batch) costs more than the arithmetic. :func:`ppo_update`
computes the same values in the same order on the same tensors, so parameters,
optimiser state, losses and the torch random stream come out bit-identical; it falls
back to ``alg.update()`` for any configuration it does not cover. What it leaves out:

- per-mini-batch gathers: the rollout is gathered once in permuted order, and rsl-rl's
  mini-batches (the same permutation in every epoch) become slices of it;
- work repeated in every epoch: the normalised advantages and old log-probabilities of
  each mini-batch are computed once;
- the actor's discarded per-mini-batch sample: only the random draw it makes is made
  (:func:`_discarded_sample`, checked once per shape against a real sample);
- ``optimizer.zero_grad``/``step`` wrappers: gradients are set to ``None`` and the fused
  Adam kernel is called directly (:class:`_DirectAdam`).
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


def _clip_grad_norms(groups: tuple[list[torch.Tensor], ...], max_norm: float) -> None:
    """``torch.nn.utils.clip_grad_norm_`` (2-norm, foreach, one CPU dtype) on each group.

    The same operations as calling it once per group, minus its wrappers, with the
    per-tensor norms of all groups taken in one ``_foreach_norm`` call.
    """
    grads = [[p.grad for p in params if p.grad is not None] for params in groups]
    flat = [g for group in grads for g in group]
    if not flat:
        return
    norms = torch._foreach_norm(flat, 2.0)
    start = 0
    for group in grads:
        if not group:
            continue
        group_norms = norms[start : start + len(group)]
        start += len(group)
        total = torch.linalg.vector_norm(torch.stack(group_norms), 2.0)
        coef = torch.clamp(float(max_norm) / (total + 1e-6), max=1.0)
        torch._foreach_mul_(group, coef)


#: (shape, dtype, device type) of a sample -> whether drawing ``exponential_`` alone moves
#: torch's random stream exactly as ``CategoricalDistribution.sample`` does (checked once each)
_SAME_STREAM: dict[tuple, bool] = {}


def _discarded_sample(dist: CategoricalDistribution) -> None:
    """Advance torch's random stream exactly as ``dist.sample()`` would, without the sample.

    On CPU ``torch.multinomial(p, 1)`` draws ``empty_like(p).exponential_()`` and takes an
    argmax; the draw alone moves the generator the same way, without the input checks, the
    argmax and the one-hot. Whether it does is checked on the first sample of each shape
    (sample, rewind, draw, compare the generator states); if not, ``dist.sample()`` is used.
    """
    log_probs = dist.logits.detach()
    key = (tuple(log_probs.shape), log_probs.dtype, log_probs.device.type)
    same = _SAME_STREAM.get(key)

    def draw() -> None:
        torch.empty_like(log_probs, memory_format=torch.contiguous_format).exponential_()

    with torch.no_grad():
        if same:
            draw()
        elif same is None and log_probs.device.type == "cpu":
            before = torch.get_rng_state()
            dist.sample()
            after = torch.get_rng_state()
            torch.set_rng_state(before)
            draw()
            _SAME_STREAM[key] = torch.equal(torch.get_rng_state(), after)
            torch.set_rng_state(after)
        else:
            dist.sample()


class _DirectAdam:
    """``step()`` of a fused :class:`torch.optim.Adam`, straight into its kernel.

    ``Optimizer.step`` spends several times the fused kernel's own time on its wrappers
    (profiling hooks, grad-mode switch, re-collecting the state of every parameter); this
    makes the same two calls it ends in (``_foreach_add_`` on the step counters, then
    ``_fused_adam_``) with the same arguments, so the numbers are the same.
    """

    def __init__(self, optimizer: torch.optim.Adam, params: list[torch.Tensor]) -> None:
        self.optimizer = optimizer
        self.group = optimizer.param_groups[0]
        state = [optimizer.state[p] for p in params]
        self.params = params
        self.exp_avgs = [s["exp_avg"] for s in state]
        self.exp_avg_sqs = [s["exp_avg_sq"] for s in state]
        self.steps = [s["step"] for s in state]

    @classmethod
    def of(cls, optimizer: Any, params: list[torch.Tensor]) -> _DirectAdam | None:
        """The direct step for ``optimizer``, or None when only ``optimizer.step()`` is exact.

        Exact for a fused Adam with one parameter group holding exactly ``params`` in that
        order, every state already created (after its first ``step()``), no AMSGrad,
        weight decay, capturable or differentiable mode and no step hooks.
        """
        from torch.optim import optimizer as optim_module

        groups = getattr(optimizer, "param_groups", ())
        if type(optimizer) is not torch.optim.Adam or len(groups) != 1:
            return None
        group = groups[0]
        same_params = len(group["params"]) == len(params) and all(
            a is b for a, b in zip(group["params"], params, strict=True)
        )
        if (
            not same_params
            or group.get("fused") is not True
            or group["amsgrad"]
            or group["weight_decay"]
            or group["capturable"]
            or group["differentiable"]
            or group.get("decoupled_weight_decay")
            or any(p.device.type != "cpu" or p.dtype != torch.float32 for p in params)
            or optimizer._optimizer_step_pre_hooks
            or optimizer._optimizer_step_post_hooks
            or optim_module._global_optimizer_pre_hooks
            or optim_module._global_optimizer_post_hooks
            or getattr(optimizer, "grad_scale", None) is not None
            or getattr(optimizer, "found_inf", None) is not None
            or not hasattr(torch, "_fused_adam_")
        ):
            return None
        state = optimizer.state
        if not all(p in state and {"exp_avg", "exp_avg_sq", "step"} <= state[p].keys()
                   for p in params):  # fmt: skip
            return None
        return cls(optimizer, params)

    def step(self) -> None:
        """One Adam step on the parameters' gradients (``optimizer.step()`` if one is missing)."""
        grads = [p.grad for p in self.params]
        if any(g is None for g in grads):
            self.optimizer.step()
            return
        group = self.group
        beta1, beta2 = group["betas"]
        with torch.no_grad():
            torch._foreach_add_(self.steps, 1)
            torch._fused_adam_(
                self.params,
                grads,
                self.exp_avgs,
                self.exp_avg_sqs,
                [],
                self.steps,
                amsgrad=False,
                lr=group["lr"],
                beta1=beta1,
                beta2=beta2,
                weight_decay=0.0,
                eps=group["eps"],
                maximize=group["maximize"],
                grad_scale=None,
                found_inf=None,
            )


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
    # rsl-rl gathers each mini-batch with ``indices[i * mb : (i + 1) * mb]`` in every epoch;
    # gathering once in permuted order makes every mini-batch a slice of the same rows
    obs_td = st.observations.flatten(0, 1)

    def permuted(tensor: torch.Tensor) -> torch.Tensor:
        return torch.index_select(tensor, 0, indices)

    obs_actor = permuted(obs_td[group])
    obs_critic = obs_actor if critic_group == group else permuted(obs_td[critic_group])
    # log pi(a|s) of the one-hot actions is ``sum(one_hot * log p)``: one nonzero term,
    # so gathering that term gives the same value and the same gradient
    action_index = permuted(st.actions.flatten(0, 1)).argmax(dim=-1, keepdim=True)
    values_old = permuted(st.values.flatten(0, 1))
    returns = permuted(st.returns.flatten(0, 1))
    old_logp = permuted(st.actions_log_prob.flatten(0, 1))
    advantages = permuted(st.advantages.flatten(0, 1))
    actor_params = list(actor.parameters())
    critic_params = list(critic.parameters())
    params = [*actor_params, *critic_params]
    adam = _DirectAdam.of(alg.optimizer, params)
    clip, vcoef, ecoef = alg.clip_param, alg.value_loss_coef, alg.entropy_coef
    # every epoch visits the same mini-batches, so what depends only on the rollout
    # (the normalised, negated advantages and the old log-probabilities) is computed once
    batches = []
    for i in range(num_mb):
        rows = slice(i * mb_size, (i + 1) * mb_size)
        adv = advantages[rows]
        if alg.normalize_advantage_per_mini_batch:
            with torch.no_grad():
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        batches.append((rows, -torch.squeeze(adv), torch.squeeze(old_logp[rows])))
    losses: list[torch.Tensor] = []
    for _ in range(num_epochs):
        for rows, neg_adv, b_old_logp in batches:
            b_values = values_old[rows]
            b_returns = returns[rows]
            # actor: logits -> log-softmax; rsl-rl draws a (discarded) sample here
            dist.update(mlp_forward(actor.mlp, obs_actor[rows]))
            _discarded_sample(dist)
            log_probs = dist.logits.gather(-1, action_index[rows]).squeeze(-1)
            values = mlp_forward(critic.mlp, obs_critic[rows])
            entropy = dist.entropy
            ratio = torch.exp(log_probs - b_old_logp)
            surrogate = neg_adv * ratio
            surrogate_clipped = neg_adv * torch.clamp(ratio, 1.0 - clip, 1.0 + clip)
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
            for p in params:  # optimizer.zero_grad() (set_to_none), without its wrappers
                p.grad = None
            loss.backward()
            _clip_grad_norms((actor_params, critic_params), alg.max_grad_norm)
            if adam is None:
                alg.optimizer.step()
            else:
                adam.step()
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
