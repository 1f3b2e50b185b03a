"""Task names and their accepted spellings, apart from `TASKS` so checking one imports no torch."""

from __future__ import annotations

import difflib
from importlib.metadata import EntryPoint, entry_points

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.task_options import ALIASES

__all__ = [
    "ALIASES",
    "BUILTIN_TASKS",
    "ENTRY_POINT_GROUP",
    "TASK_NAMES",
    "canonical_name",
    "task_entry_points",
    "task_names",
]

#: The short names of the paper's tasks, in the order they are listed.
TASK_NAMES: tuple[str, ...] = ("findmilk", "driving")
#: The tasks shipped in this package: the paper's and the third-party adapters.
BUILTIN_TASKS: tuple[str, ...] = (*TASK_NAMES, "smartgrid")
#: Entry-point group under which an installed package publishes a task class.
ENTRY_POINT_GROUP = "amuled_ma.tasks"


def task_entry_points() -> dict[str, EntryPoint]:
    """Installed ``amuled_ma.tasks`` entry points by lower-case name (built-in names win)."""
    found = {ep.name.strip().lower(): ep for ep in entry_points(group=ENTRY_POINT_GROUP)}
    return {name: ep for name, ep in found.items() if name not in BUILTIN_TASKS}


def task_names() -> tuple[str, ...]:
    """The built-in tasks, then the installed entry-point tasks (sorted)."""
    return (*BUILTIN_TASKS, *sorted(task_entry_points()))


def canonical_name(name: str) -> str:
    """Return the short task name for a short name, alias or Gymnasium id (any capitalisation).

    Raises:
        ScenarioError: Not a string, or an unknown task; the message lists the known ones
            and the closest.
    """
    if not isinstance(name, str):
        raise ScenarioError(f"name: expected a task name, got {name!r}")
    key = name.strip().lower()
    key = ALIASES.get(key, key)
    known = task_names()
    if key not in known:
        close = difflib.get_close_matches(key, [*known, *ALIASES], n=1)
        hint = f"; did you mean {ALIASES.get(close[0], close[0])}?" if close else ""
        raise ScenarioError(
            f"name: unknown task {name!r}; known tasks: {', '.join(known)} (more through "
            f"the {ENTRY_POINT_GROUP!r} entry-point group, docs/tasks.md){hint}"
        )
    return key
