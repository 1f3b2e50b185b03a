"""The KL anchor of fine-tuning, in two recipes: the paper's equation and the authors' code.

Fine-tuning rewards ``f(B)[a_t] - lambda_KL * anchor_t``; the recipe
(``[finetune].recipe``) decides the anchor.

- ``"equation"`` (the paper's equation, our default): the per-sample estimator of
  ``KL(pi || pi_base)``, ``anchor_t = log pi(a_t|s_t) - log pi_base(a_t|s_t)``
  (:func:`per_sample_kl`). Its expectation over ``a_t ~ pi`` is the KL divergence, and it
  tells PPO which actions move the policy away from the base.
- ``"authors"`` (what the authors' scripts compute, ``algorithms/finetune_moral.py:153-177``
  and ``kl_sensitivity.py:141-149`` of ``temetski/moral_agent``): the log-probabilities of
  the *taken* actions since the window began, under the fine-tuned and under the frozen
  base policy, are each passed through a log-softmax **over time**, and ``anchor_t`` is the
  KL divergence between the two with PyTorch ``KLDivLoss(reduction="sum",
  log_target=True)`` semantics, input the fine-tuned and target the base sequence::

      p = log_softmax([log pi(a_k|s_k)      for k in window])
      q = log_softmax([log pi_base(a_k|s_k) for k in window])
      anchor_t = sum_k exp(q_k) * (q_k - p_k)          # KL(q || p) over time steps

  The window is every step of the current episode **and** the current iteration: the
  authors clear their lists when an episode ends and at the start of every rollout, so
  the first step of a window always has ``anchor = 0`` (:class:`EpisodeWindowKL`). The
  whole window is recomputed each step and charged to the current step. It is not a KL
  between policies: it compares how the two policies rank the actions already taken.
"""

from __future__ import annotations

import torch

#: The recipes of ``[finetune].recipe``.
RECIPES = ("equation", "authors")


def per_sample_kl(logp: torch.Tensor, logp_base: torch.Tensor) -> torch.Tensor:
    """``log pi(a|s) - log pi_base(a|s)`` per sample (the ``"equation"`` anchor) ``[N]``."""
    return logp - logp_base


def window_kl(logp: torch.Tensor, logp_base: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The authors' anchor for windows of steps, one window per row.

    Args:
        logp: ``[N, T]`` log-probabilities of the taken actions under the fine-tuned policy.
        logp_base: ``[N, T]`` the same actions under the base policy.
        mask: ``[N, T]`` bool, True where a step belongs to the row's window (every row
            has at least one).

    Returns:
        ``[N]``: ``KLDivLoss(reduction="sum", log_target=True)(log_softmax(logp),
        log_softmax(logp_base))`` over each row's masked steps.

    """
    neg_inf = torch.tensor(float("-inf"), dtype=logp.dtype)
    p = torch.log_softmax(torch.where(mask, logp, neg_inf), dim=-1)
    q = torch.log_softmax(torch.where(mask, logp_base, neg_inf), dim=-1)
    terms = torch.where(mask, q.exp() * (q - p), torch.zeros((), dtype=logp.dtype))
    return terms.sum(dim=-1)


class EpisodeWindowKL:
    """The authors' anchor, step by step, for ``num_envs`` copies at once.

    Call :meth:`start_iteration` before each rollout, :meth:`step` once per env step with
    the taken actions' log-probabilities (it returns the anchor of that step), and
    :meth:`end_episodes` with the step's done flags.

    Args:
        num_envs: Environment copies.
        capacity: Longest window (the rollout length: windows never outlive an iteration).

    """

    def __init__(self, num_envs: int, capacity: int) -> None:
        self.logp = torch.zeros(num_envs, capacity, dtype=torch.float64)
        self.logp_base = torch.zeros(num_envs, capacity, dtype=torch.float64)
        self.length = torch.zeros(num_envs, dtype=torch.long)
        self._positions = torch.arange(capacity)
        self._rows = torch.arange(num_envs)

    def start_iteration(self) -> None:
        """Empty every window (the authors' lists are re-created each rollout)."""
        self.length.zero_()

    def step(self, logp: torch.Tensor, logp_base: torch.Tensor) -> torch.Tensor:
        """Append this step's log-probabilities; return the anchor ``[N]`` of the step.

        Raises:
            RuntimeError: A window outgrew ``capacity`` (call :meth:`start_iteration`).

        """
        if int(self.length.max()) >= self.logp.shape[1]:
            raise RuntimeError("a KL window outgrew the rollout; call start_iteration()")
        self.logp[self._rows, self.length] = logp.to(torch.float64)
        self.logp_base[self._rows, self.length] = logp_base.to(torch.float64)
        self.length += 1
        mask = self._positions.unsqueeze(0) < self.length.unsqueeze(1)
        return window_kl(self.logp, self.logp_base, mask).to(logp.dtype)

    def end_episodes(self, dones: torch.Tensor) -> None:
        """Empty the windows of the copies whose episode ended at this step."""
        self.length[dones.reshape(-1).bool()] = 0
