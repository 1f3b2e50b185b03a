"""Task names: the short name of each task and the other spellings accepted for it.

Kept apart from the task registry (`TASKS`), which imports the task
classes, so that what only needs a task's name (its prompt template, the rule-based human,
the demonstrators) can check it without importing torch or a task.
"""

from __future__ import annotations

import difflib

from amuled_ma.errors import ScenarioError

__all__ = ["ALIASES", "TASK_NAMES", "canonical_name"]

#: The short names of the tasks, in the order they are listed.
TASK_NAMES: tuple[str, ...] = ("findmilk", "driving")
#: Other spellings of a task name (compared lower-case) -> its short name.
ALIASES: dict[str, str] = {
    "amuled/findmilk-v0": "findmilk",
    "find_milk": "findmilk",
    "amuled/driving-v0": "driving",
    "driving_and_rescuing": "driving",
}


def canonical_name(name: str) -> str:
    """Return the short task name for ``name`` (short name, alias or Gymnasium id).

    Args:
        name: A short name, an alias or a Gymnasium id, in any capitalisation.

    Returns:
        The short name (``"findmilk"`` or ``"driving"``).

    Raises:
        ScenarioError: Not a string, or an unknown task; the message lists the known ones
            and the closest (:func:`difflib.get_close_matches`).

    """
    if not isinstance(name, str):
        raise ScenarioError(f"name: expected a task name, got {name!r}")
    key = name.strip().lower()
    key = ALIASES.get(key, key)
    if key not in TASK_NAMES:
        close = difflib.get_close_matches(key, [*TASK_NAMES, *ALIASES], n=1)
        hint = f"; did you mean {ALIASES.get(close[0], close[0])}?" if close else ""
        raise ScenarioError(
            f"name: unknown task {name!r}; known tasks: {', '.join(TASK_NAMES)}{hint}"
        )
    return key
