"""Task names: the short name of each task and the other spellings accepted for it.

Kept apart from the task registry (`TASKS`), which imports the task
classes, so that what only needs a task's name (its prompt template, the rule-based human,
the demonstrators) can check it without importing torch or a task.

A task is built in (`BUILTIN_TASKS`) or published by an installed package under the
entry-point group ``amuled_ma.tasks`` (`ENTRY_POINT_GROUP`); reading the group
imports nothing.
"""

from __future__ import annotations

import difflib
from importlib.metadata import EntryPoint, entry_points

from amuled_ma.errors import ScenarioError

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
#: Other spellings of a task name (compared lower-case) -> its short name.
ALIASES: dict[str, str] = {
    "amuled/findmilk-v0": "findmilk",
    "find_milk": "findmilk",
    "amuled/driving-v0": "driving",
    "driving_and_rescuing": "driving",
    "smart_grid": "smartgrid",
    "ethical-smart-grid": "smartgrid",
}


def task_entry_points() -> dict[str, EntryPoint]:
    """Installed ``amuled_ma.tasks`` entry points by lower-case name (built-in names win)."""
    found = {ep.name.strip().lower(): ep for ep in entry_points(group=ENTRY_POINT_GROUP)}
    return {name: ep for name, ep in found.items() if name not in BUILTIN_TASKS}


def task_names() -> tuple[str, ...]:
    """The built-in tasks, then the installed entry-point tasks (sorted)."""
    return (*BUILTIN_TASKS, *sorted(task_entry_points()))


def canonical_name(name: str) -> str:
    """Return the short task name for ``name`` (short name, alias or Gymnasium id).

    Args:
        name: A short name, an alias or a Gymnasium id, in any capitalisation.

    Returns:
        The short name (``"findmilk"``, ``"driving"``, ``"smartgrid"`` or an installed
        entry point's name).

    Raises:
        ScenarioError: Not a string, or an unknown task; the message lists the known ones
            and the closest (:func:`difflib.get_close_matches`).

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
