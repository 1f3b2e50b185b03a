"""The KL anchor of fine-tuning, ``r_t = f(B)[a_t] - lambda_KL * anchor_t``, in two recipes.

``"equation"``: the paper's per-sample estimator; ``"authors"``: ``finetune_moral.py:153-177``'s
KL over the episode's window (docs/learning.md, "Two recipes").
"""

from __future__ import annotations

import torch


def per_sample_kl(logp: torch.Tensor, logp_base: torch.Tensor) -> torch.Tensor:
    """``log pi(a|s) - log pi_base(a|s)`` per sample (the ``"equation"`` anchor) ``[N]``."""
    return logp - logp_base


def window_kl(logp: torch.Tensor, logp_base: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The authors' anchor ``[N]`` for windows of steps ``[N, T]``, one window per row.

    ``mask`` is True where a step belongs to the row's window (at least one per row).
    """
    neg_inf = torch.tensor(float("-inf"), dtype=logp.dtype)
    p = torch.log_softmax(torch.where(mask, logp, neg_inf), dim=-1)
    q = torch.log_softmax(torch.where(mask, logp_base, neg_inf), dim=-1)
    terms = torch.where(mask, q.exp() * (q - p), torch.zeros((), dtype=logp.dtype))
    return terms.sum(dim=-1)


class EpisodeWindowKL:
    """The authors' anchor, step by step, for ``num_envs`` copies at once (a CPU tensor book).

    Call `start_iteration` before each rollout, `step` once per env step and `end_episodes`
    with its done flags; ``capacity`` is the rollout length.
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
            RuntimeError: A window outgrew ``capacity`` (call `start_iteration`).
        """
        if int(self.length.max()) >= self.logp.shape[1]:
            raise RuntimeError("a KL window outgrew the rollout; call start_iteration()")
        self.logp[self._rows, self.length] = logp.to("cpu", torch.float64)
        self.logp_base[self._rows, self.length] = logp_base.to("cpu", torch.float64)
        self.length += 1
        mask = self._positions.unsqueeze(0) < self.length.unsqueeze(1)
        return window_kl(self.logp, self.logp_base, mask).to(logp.device, logp.dtype)

    def end_episodes(self, dones: torch.Tensor) -> None:
        """Empty the windows of the copies whose episode ended at this step."""
        self.length[dones.reshape(-1).bool().cpu()] = 0
