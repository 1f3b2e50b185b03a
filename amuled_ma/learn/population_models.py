"""A population's actor and critic: P networks of one shape, stacked, as rsl-rl models.

Each ``nn.Linear`` becomes a `StackedLinear` (weight ``[P, out, in]``) under the same name; a
batch is member-major: ``P`` blocks of ``B`` rows, block ``p`` member ``p``'s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn as nn
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from amuled_ma.learn.distribution import CategoricalDistribution


class MemberStreams:
    """One CPU random generator per member: the population's stand-in for torch's global one.

    Member ``p`` makes a lone run's calls in the same order from generator ``p``, set to the
    lone run's state, so it draws the same numbers.
    """

    def __init__(self, population: int) -> None:
        self.population = int(population)
        self.generators = [torch.Generator() for _ in range(self.population)]
        # uniforms drawn ahead (`reserve`): [calls, P x rows, 1], the next call's index
        self.reserved: torch.Tensor | None = None
        self.next = 0

    def __deepcopy__(self, memo: dict) -> MemberStreams:
        """Copies of a model share its streams (a frozen copy never draws)."""
        return self

    def get_states(self) -> list[torch.Tensor]:
        """Each generator's state (a lone run's ``torch.get_rng_state()``)."""
        return [g.get_state() for g in self.generators]

    def set_states(self, states: Sequence[torch.Tensor]) -> None:
        """Set each generator's state (``torch.get_rng_state()`` of each lone run)."""
        for generator, state in zip(self.generators, states, strict=True):
            generator.set_state(state)

    def reserve(self, each: int, calls: int, dtype: torch.dtype, device: torch.device) -> None:
        """Draw the next ``calls`` calls of `uniform` (``each`` per member) at once.

        torch's CPU generator fills element by element: the numbers of ``calls`` draws.
        """
        blocks = [torch.rand((calls, each, 1), dtype=dtype, generator=g) for g in self.generators]
        self.reserved = torch.stack(blocks, dim=1).reshape(calls, -1, 1).to(device)
        self.next = 0

    def uniform(self, rows: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        """``[rows, 1]`` uniforms in ``[0, 1)``: ``rows / P`` from each member, member-major.

        Raises:
            RuntimeError: Another draw than the one `reserve` drew ahead.
        """
        reserved = self.reserved
        if reserved is not None:
            if reserved.shape[1] != rows or reserved.dtype != dtype:
                raise RuntimeError("a draw of other uniforms than those reserved ahead")
            out = reserved[self.next]
            self.next += 1
            if self.next == reserved.shape[0]:
                self.reserved = None
            return out
        each = rows // self.population
        draws = [torch.rand((each, 1), dtype=dtype, generator=g) for g in self.generators]
        return torch.cat(draws).to(device)

    def permutations(self, n: int, device: torch.device) -> torch.Tensor:
        """``[P, n]``: a random permutation of ``0..n-1`` from each member's stream.

        Raises RuntimeError: uniforms reserved ahead are not used up (they come first).
        """
        if self.reserved is not None:
            raise RuntimeError("a permutation drawn before the uniforms reserved ahead")
        return torch.stack([torch.randperm(n, generator=g) for g in self.generators]).to(device)


class PopulationCategoricalDistribution(CategoricalDistribution):
    """The categorical head, sampling each member from its ``streams`` (set by `PopulationPPO`)."""

    def __init__(self, output_dim: int, init_last_layer_std: float = 0.01) -> None:
        super().__init__(output_dim, init_last_layer_std)
        self.streams: MemberStreams | None = None

    def sample(self) -> torch.Tensor:
        """One action per row, one-hot; row block ``p`` drawn from member ``p``'s stream."""
        assert self.streams is not None
        cdf = self.probs.cumsum(-1)
        return self._action_at(cdf, self.streams.uniform(cdf.shape[0], cdf.dtype, cdf.device))


class StackedLinear(nn.Module):
    """``population`` linear layers of one shape; ``weight[p]`` is member ``p``'s weight."""

    def __init__(self, population: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.population = int(population)
        self.in_features = int(in_features)
        self.out_features = int(out_features)
        self.weight = nn.Parameter(torch.empty(population, out_features, in_features))
        self.bias = nn.Parameter(torch.empty(population, out_features))

    @classmethod
    def copies_of(cls, layer: nn.Linear, population: int) -> StackedLinear:
        """``population`` copies of ``layer`` (its weights in every member)."""
        stacked = cls(population, layer.in_features, layer.out_features)
        with torch.no_grad():
            stacked.weight.copy_(layer.weight.expand(population, -1, -1))
            stacked.bias.copy_(layer.bias.expand(population, -1))
        return stacked.to(layer.weight.device)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``[P * B, in] -> [P * B, out]``, block ``p`` through member ``p``'s layer."""
        out = self.blocks(x.reshape(self.population, -1, self.in_features))
        return out.reshape(-1, self.out_features)

    def blocks(self, x: torch.Tensor) -> torch.Tensor:
        """``[P, B, in] -> [P, B, out]``: one batched matmul, ``x[p] @ weight[p].T + bias[p]``."""
        return torch.baddbmm(self.bias.unsqueeze(1), x, self.weight.transpose(1, 2))

    def extra_repr(self) -> str:
        """The shape, as ``nn.Linear`` shows it, with the population."""
        return (
            f"population={self.population}, in_features={self.in_features}, "
            f"out_features={self.out_features}"
        )


class StackedMLP(nn.Sequential):
    """An MLP of `StackedLinear` layers on ``[P, B, features]`` blocks, the lone MLP's indices."""

    def __init__(self, population: int, *layers: nn.Module) -> None:
        super().__init__(*layers)
        self.population = int(population)
        # every child in order, an activation the lone MLP shares between layers included
        self.steps: list[tuple[bool, Any]] = [(isinstance(m, StackedLinear), m) for m in layers]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``[P * B, in] -> [P * B, out]``, block ``p`` through member ``p``'s layers."""
        x = x.reshape(self.population, -1, x.shape[-1])
        for linear, module in self.steps:
            x = module.blocks(x) if linear else module(x)
        return x.reshape(-1, x.shape[-1])


class PopulationMLPModel(MLPModel):
    """rsl-rl's MLP model for ``population`` members at once (``P x B`` member-major rows)."""

    def __init__(
        self,
        obs: TensorDict,
        obs_groups: dict[str, list[str]],
        obs_set: str,
        output_dim: int,
        population: int = 1,
        **kwargs: Any,
    ) -> None:
        super().__init__(obs, obs_groups, obs_set, output_dim, **kwargs)
        self.population = int(population)
        # the same layers, each nn.Linear as P stacked copies (an activation shared: kept)
        self.mlp: StackedMLP = StackedMLP(
            self.population,
            *[
                StackedLinear.copies_of(m, self.population) if isinstance(m, nn.Linear) else m
                for m in self.mlp
            ],
        )
        #: The output of the last forward pass (detached): the critic's values of the
        #: mini-batch being updated, read for each member's value loss.
        self.last_output: torch.Tensor | None = None

    def forward(self, obs: TensorDict, *args: Any, **kwargs: Any) -> torch.Tensor:
        """rsl-rl's forward pass over ``P x B`` member-major rows; keeps ``last_output``."""
        out = super().forward(obs, *args, **kwargs)
        self.last_output = out.detach()
        return out


def stack_states(states: Sequence[Mapping[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The state dict ``{key: [P, ...]}`` of a population model from its members' lone ones."""
    return {key: torch.stack([state[key] for state in states]) for key in states[0]}


def member_state(state: Mapping[str, torch.Tensor], member: int) -> dict[str, torch.Tensor]:
    """Member ``member``'s lone state dict (rsl-rl's ``MLPModel`` format) from a population's."""
    return {key: value[member].clone() for key, value in state.items()}
