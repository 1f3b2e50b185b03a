"""Deliberation: the moral panel the learner asks every step, and the PettingZoo env."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from amuled_ma.deliberation.panel import MoralPanel, PanelOutput, PanelStats

if TYPE_CHECKING:
    from amuled_ma.deliberation.env import DeliberationEnv

__all__ = [
    "DeliberationEnv",
    "MoralPanel",
    "PanelOutput",
    "PanelStats",
    "project_to_simplex",
]

# names served by amuled_ma.deliberation.env, imported on first use
_ENV_NAMES = frozenset({"DeliberationEnv", "project_to_simplex"})


def __getattr__(name: str) -> Any:
    """Import the PettingZoo side on first use (the panel does not need it)."""
    if name in _ENV_NAMES:
        from amuled_ma.deliberation import env

        return getattr(env, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
