"""Code for the per-agent source tests, imported by ``module:Class`` strings.

The tests put this folder on ``sys.path`` and name ``amuled_agent_helper:FixedAgent`` (an
entry-point agent) or ``amuled_agent_helper:TinyNet`` (a policy network's class);
:func:`install_fixed_entry_point` makes ``FixedAgent`` an installed plug-in.
"""

from __future__ import annotations

from collections.abc import Sequence
from importlib.metadata import EntryPoint
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from amuled_ma.beliefs import BeliefRequest, BeliefResult, BeliefSource

if TYPE_CHECKING:
    import pytest


class FixedAgent(BeliefSource):
    """A plug-in agent: a one-hot belief on ``index`` for every request; counts its calls."""

    name = "fixed-agent"
    needs_messages = False
    calls: list[int] = []  # noqa: RUF012 - shared on purpose: sizes of every batch asked

    def __init__(self, index: int = 0) -> None:
        self.index = index

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Answer every request with the same one-hot belief."""
        FixedAgent.calls.append(len(requests))
        return [BeliefResult(np.eye(r.num_actions)[self.index], "ok", self.name) for r in requests]


def install_fixed_entry_point(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ``fixed`` an installed ``amuled_ma.agents`` entry point naming :class:`FixedAgent`.

    The only entry point of that group :mod:`amuled_ma.clusters.plugins` sees, for the test.
    """
    point = EntryPoint("fixed", "amuled_agent_helper:FixedAgent", "amuled_ma.agents")
    monkeypatch.setattr(
        "amuled_ma.clusters.plugins.entry_points",
        lambda group: [point] if group == "amuled_ma.agents" else [],
    )


def not_a_source(**_: Any) -> object:
    """A factory returning something that is no belief source."""
    return object()


class TinyNet(torch.nn.Module):
    """A policy network with a named layout (not an inferable ``<i>.weight`` MLP)."""

    def __init__(self, obs_dim: int = 8, actions: int = 4, scale: float = 1.0) -> None:
        super().__init__()
        self.body = torch.nn.Linear(obs_dim, 6)
        self.head = torch.nn.Linear(6, actions)
        self.scale = scale

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Logits, one per action."""
        return self.scale * self.head(torch.relu(self.body(obs)))
