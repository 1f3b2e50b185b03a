"""A categorical action distribution for rsl-rl: one-hot action rows, the MLP's output logits."""

from __future__ import annotations

import torch
import torch.nn as nn
from rsl_rl.modules.distribution import Distribution


class CategoricalDistribution(Distribution):
    """Categorical distribution over ``output_dim`` actions, one-hot encoded.

    ``init_last_layer_std`` is the logits layer's orthogonal gain (CleanRL: 0.01, near uniform).
    """

    def __init__(self, output_dim: int, init_last_layer_std: float = 0.01) -> None:
        super().__init__(output_dim)
        self.init_last_layer_std = init_last_layer_std
        self._log_probs: torch.Tensor | None = None

    def update(self, mlp_output: torch.Tensor) -> None:
        """Set the distribution from the MLP's logits."""
        self._log_probs = torch.log_softmax(mlp_output, dim=-1)

    def _last_log_probs(self) -> torch.Tensor:
        """The log-probabilities of the last `update`; ``RuntimeError`` before any."""
        if self._log_probs is None:
            raise RuntimeError("CategoricalDistribution: read before update() set it")
        return self._log_probs

    def sample(self) -> torch.Tensor:
        """Sample one action per row, one-hot, by inverse CDF (3x cheaper than multinomial)."""
        cdf = self.probs.cumsum(-1)
        u = torch.rand((*cdf.shape[:-1], 1), dtype=cdf.dtype, device=cdf.device)
        return self._action_at(cdf, u)

    def _action_at(self, cdf: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The one-hot action of each row whose CDF interval holds ``u`` ``[..., 1]``."""
        index = (cdf < u).sum(-1, keepdim=True).clamp_max(self.output_dim - 1)
        return torch.zeros_like(cdf).scatter_(-1, index, 1.0)

    def deterministic_output(self, mlp_output: torch.Tensor) -> torch.Tensor:
        """Return the most likely action, one-hot; it also sets the distribution, like `update`."""
        self.update(mlp_output)
        index = mlp_output.argmax(dim=-1)
        return torch.nn.functional.one_hot(index, self.output_dim).to(mlp_output.dtype)

    def as_deterministic_output_module(self) -> nn.Module:
        """Return an export-friendly argmax-to-one-hot module."""
        return _ArgmaxOneHot(self.output_dim)

    @property
    def input_dim(self) -> int:
        """The MLP outputs one logit per action."""
        return self.output_dim

    @property
    def probs(self) -> torch.Tensor:
        """Action probabilities, shape ``[..., output_dim]``."""
        return self._last_log_probs().exp()

    @property
    def mean(self) -> torch.Tensor:
        """Mean of the one-hot vector, i.e. the action probabilities."""
        return self.probs

    @property
    def std(self) -> torch.Tensor:
        """Per-component standard deviation of the one-hot vector, ``sqrt(p (1 - p))``."""
        p = self.probs
        return (p * (1.0 - p)).sqrt()

    @property
    def entropy(self) -> torch.Tensor:
        """Entropy ``-sum p log p`` per row."""
        log_p = self._last_log_probs()
        return -(log_p.exp() * log_p).sum(dim=-1)

    @property
    def params(self) -> tuple[torch.Tensor, ...]:
        """The normalised log-probabilities (stored by rsl-rl for its KL schedule)."""
        return (self._last_log_probs(),)

    def log_prob(self, outputs: torch.Tensor) -> torch.Tensor:
        """Log-probability of one-hot actions, ``sum(one_hot * log p)`` per row."""
        return (outputs * self._last_log_probs()).sum(dim=-1)

    def kl_divergence(
        self, old_params: tuple[torch.Tensor, ...], new_params: tuple[torch.Tensor, ...]
    ) -> torch.Tensor:
        """Closed-form ``KL(old || new) = sum p_old (log p_old - log p_new)`` per row."""
        (old,) = old_params
        (new,) = new_params
        return (old.exp() * (old - new)).sum(dim=-1)

    def init_mlp_weights(self, mlp: nn.Module) -> None:
        """`orthogonal_init` with the logits layer's gain ``init_last_layer_std``."""
        orthogonal_init(mlp, self.init_last_layer_std)


class _ArgmaxOneHot(nn.Module):
    def __init__(self, num_actions: int) -> None:
        super().__init__()
        self.num_actions = num_actions

    def forward(self, mlp_output: torch.Tensor) -> torch.Tensor:
        index = mlp_output.argmax(dim=-1)
        return torch.nn.functional.one_hot(index, self.num_actions).to(mlp_output.dtype)


def orthogonal_init(mlp: nn.Module, last_std: float = 1.0) -> None:
    """Initialise an MLP as CleanRL does: gain ``sqrt(2)``, ``last_std`` for the output layer."""
    linears = [m for m in mlp.modules() if isinstance(m, nn.Linear)]
    for i, layer in enumerate(linears):
        nn.init.orthogonal_(layer.weight, gain=last_std if i == len(linears) - 1 else 2**0.5)
        nn.init.zeros_(layer.bias)
