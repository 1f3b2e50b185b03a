"""Code-backed agents: the ``amuled_ma.agents`` entry-point group.

A moral cluster is normally a TOML file (no code). Agents that need code, such as rule
policies or a human answering at the terminal, are :class:`~amuled_ma.beliefs.types.BeliefSource`
factories published by any installed package under the entry-point group
``amuled_ma.agents``::

    # the plug-in package's pyproject.toml
    [project.entry-points."amuled_ma.agents"]
    terminal_human = "my_pkg.human:TerminalHumanSource"

The object behind the entry point is called with the source options (keyword arguments)
and must return a ``BeliefSource``. ``make_source(kind)`` falls back to this group for
kinds it does not know, and ``amuled clusters list`` shows the registered names.
"""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points
from typing import Any

#: Name of the entry-point group of code-backed agents.
ENTRY_POINT_GROUP = "amuled_ma.agents"


def agent_entry_points() -> dict[str, EntryPoint]:
    """Every installed entry point of the ``amuled_ma.agents`` group, by name."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def load_agent(name: str) -> Any:
    """Load the factory registered under ``name`` in the ``amuled_ma.agents`` group.

    Raises:
        KeyError: No installed package registers ``name``.

    """
    points = agent_entry_points()
    if name not in points:
        raise KeyError(name)
    return points[name].load()
