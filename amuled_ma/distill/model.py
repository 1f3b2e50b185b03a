"""The distilled reward model: an ensemble of small MLPs predicting each panel member's belief."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

#: Largest share by which the loss must fall over `_WINDOW` steps to keep fitting.
_TOLERANCE = 1e-3
#: Steps between two early-stop checks.
_WINDOW = 25


@dataclass(frozen=True)
class FitSettings:
    """How the ensemble is built and fitted (Adam steps, full batch).

    ``ensemble`` 1 has no disagreement (the novelty term alone); ``weight_decay`` is an L2 penalty
    on the weights divided by the training states, a prior that weakens as answers arrive
    (0.25 measured in docs/distill.md).
    """

    ensemble: int = 5
    hidden: int = 64
    steps: int = 400
    learning_rate: float = 1e-2
    weight_decay: float = 0.25


class EnsembleModel:
    """An ensemble of MLPs, one softmax head per panel member (``members`` in head order).

    ``trained``: ``(K,)`` bool, the members answered in the last fit (the model answers for them).
    """

    def __init__(
        self, members: Sequence[str], num_actions: int, settings: FitSettings | None = None
    ) -> None:
        self.members = tuple(members)
        self.num_actions = int(num_actions)
        self.settings = settings or FitSettings()
        self.trained = np.zeros(len(self.members), dtype=bool)
        self._params: list[torch.Tensor] | None = None
        self._mean: torch.Tensor | None = None
        self._std: torch.Tensor | None = None

    @property
    def fitted(self) -> bool:
        """Whether `fit` ran with at least one answer."""
        return self._params is not None and bool(self.trained.any())

    @torch.inference_mode(False)
    @torch.enable_grad()
    def fit(self, obs: np.ndarray, beliefs: np.ndarray, mask: np.ndarray, seed: int) -> None:
        """Fit every network from scratch to the members' beliefs (gradients on in inference mode).

        ``obs`` ``(N, D)``, ``beliefs`` ``(N, K, A)``, ``mask`` ``(N, K)`` (the member answered);
        ``seed`` seeds the weights and the Poisson(1) bootstrap. `ValueError`: other shapes.
        """
        obs = np.asarray(obs, dtype=np.float64)
        beliefs = np.asarray(beliefs, dtype=np.float64)
        mask = np.asarray(mask, dtype=bool)
        n, k, a = beliefs.shape if beliefs.ndim == 3 else (0, 0, 0)
        if obs.ndim != 2 or len(obs) != n or (k, a) != (len(self.members), self.num_actions):
            raise ValueError(
                f"fit: obs {obs.shape}, beliefs {beliefs.shape}, mask {mask.shape} do not "
                f"match {len(self.members)} members x {self.num_actions} actions"
            )
        if mask.shape != (n, k):
            raise ValueError(f"fit: mask has shape {mask.shape}, expected {(n, k)}")
        s = self.settings
        gen = torch.Generator().manual_seed(int(seed) % (2**63))
        x = torch.as_tensor(obs, dtype=torch.float32)
        mean = x.mean(0, keepdim=True) if n else torch.zeros(1, obs.shape[1])
        std = x.std(0, unbiased=False, keepdim=True) if n > 1 else torch.ones(1, obs.shape[1])
        std = torch.where(std > 1e-6, std, torch.ones_like(std))
        self._mean, self._std = mean, std
        x = (x - mean) / std
        target = torch.as_tensor(np.where(mask[..., None], beliefs, 0.0), dtype=torch.float32)
        m = torch.as_tensor(mask, dtype=torch.float32)
        params = _init_params(gen, s.ensemble, obs.shape[1], s.hidden, k * a)
        if s.ensemble > 1:  # bootstrap: each network sees its own resample of the states
            counts = torch.poisson(torch.ones(s.ensemble, n), generator=gen)
            empty = counts.sum(1) == 0
            counts[empty] = 1.0
        else:
            counts = torch.ones(1, n)
        weight = counts[:, :, None] * m[None]  # (E, N, K)
        norm = weight.sum((1, 2)).clamp_min(1e-12)
        optimiser = torch.optim.Adam(params, lr=s.learning_rate)
        decay = s.weight_decay / max(n, 1)
        previous = math.inf
        for step in range(1, s.steps + 1):
            optimiser.zero_grad(set_to_none=True)
            logp = _forward(params, x).reshape(s.ensemble, n, k, a).log_softmax(-1)
            ce = -(target[None] * logp).sum(-1)  # -sum_a p(a) log q(a), (E, N, K)
            loss = ((ce * weight).sum((1, 2)) / norm).sum()
            loss = loss + decay * sum((w * w).sum() for w in params[0::2])
            loss.backward()
            optimiser.step()
            loss_value = float(loss.detach())
            if step % _WINDOW == 0:
                if previous - loss_value < _TOLERANCE * abs(previous):
                    break
                previous = loss_value
        self._params = [p.detach() for p in params]
        self.trained = np.asarray(mask.any(axis=0)) if n else np.zeros(k, dtype=bool)

    def predict_ensemble(self, obs: np.ndarray) -> np.ndarray:
        """Every network's beliefs ``(E, N, K, A)`` float64; RuntimeError before the first `fit`."""
        if self._params is None or self._mean is None or self._std is None:
            raise RuntimeError("the distilled model was never fitted")
        obs = np.asarray(obs, dtype=np.float64)
        e, k, a = self.settings.ensemble, len(self.members), self.num_actions
        if len(obs) == 0:
            return np.zeros((e, 0, k, a))
        with torch.no_grad():
            x = (torch.as_tensor(obs, dtype=torch.float32) - self._mean) / self._std
            logits = _forward(self._params, x).reshape(e, len(obs), k, a)
            probs = logits.double().softmax(-1).numpy()
        return probs / probs.sum(-1, keepdims=True)

    def predict(self, obs: np.ndarray) -> np.ndarray:
        """The ensemble's mean belief per member, ``(N, K, A)`` float64 (rows sum to 1)."""
        mean = self.predict_ensemble(obs).mean(0)
        return mean / mean.sum(-1, keepdims=True)


def _init_params(
    gen: torch.Generator, ensemble: int, inputs: int, hidden: int, outputs: int
) -> list[torch.Tensor]:
    """``[W1, b1, W2, b2, W3, b3]`` of ``ensemble`` networks (LeCun-normal weights)."""
    params = []
    for fan_in, fan_out, gain in ((inputs, hidden, 1.0), (hidden, hidden, 1.0),
                                  (hidden, outputs, 0.1)):  # fmt: skip
        w = torch.randn(ensemble, fan_in, fan_out, generator=gen) * (gain / math.sqrt(fan_in))
        params += [w.requires_grad_(), torch.zeros(ensemble, 1, fan_out, requires_grad=True)]
    return params


def _forward(params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Logits ``(E, N, outputs)`` of every network for standardised ``x`` ``(N, D)``."""
    w1, b1, w2, b2, w3, b3 = params
    h = x.unsqueeze(0).expand(w1.shape[0], -1, -1)
    h = torch.tanh(torch.baddbmm(b1, h, w1))
    h = torch.tanh(torch.baddbmm(b2, h, w2))
    return torch.baddbmm(b3, h, w3)
