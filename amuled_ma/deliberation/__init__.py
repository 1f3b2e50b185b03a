"""Deliberation: the moral panel the learner asks every step, and the PettingZoo env."""

from __future__ import annotations

from typing import Any

from amuled_ma.deliberation.panel import MoralPanel, PanelOutput, PanelStats

__all__ = ["DeliberationEnv", "MoralPanel", "PanelOutput", "PanelStats", "project_to_simplex"]


def __getattr__(name: str) -> Any:
    """Import the PettingZoo side (`amuled_ma.deliberation.env`) on first use."""
    if name in ("DeliberationEnv", "project_to_simplex"):
        from amuled_ma.deliberation import env

        return getattr(env, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
