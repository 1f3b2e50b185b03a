"""Task environments of the paper: FindMilk and Driving-and-Rescuing.

Each task exists twice over one implementation:

- a batched torch core (:class:`~amuled_ma.tasks.base.BatchedTask`): ``num_envs`` copies
  stepped by one call, with automatic reset and per-episode metrics, for the learner;
- a Gymnasium view (``gymnasium.make("amuled/FindMilk-v0")``, ``"amuled/Driving-v0"``),
  the same core with ``num_envs=1``, for checkers, prompts and humans.

Usage::

    from amuled_ma.tasks import make_batched
    task = make_batched("driving", 4096, seed=0, shaping_coef=1.0)
    obs = task.reset()
    obs, reward, terminated, truncated, info = task.step(actions)

This package imports torch lazily: ``import amuled_ma`` only registers the Gymnasium ids.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from amuled_ma.errors import ScenarioError

if TYPE_CHECKING:
    from amuled_ma.tasks.base import BatchedTask
    from amuled_ma.tasks.driving import Driving
    from amuled_ma.tasks.findmilk import FindMilk

__all__ = ["TASKS", "BatchedTask", "Driving", "FindMilk", "get_task", "make_batched"]

# task name -> "module:Class" of its batched core
_ENTRY_POINTS: dict[str, str] = {
    "findmilk": "amuled_ma.tasks.findmilk:FindMilk",
    "driving": "amuled_ma.tasks.driving:Driving",
}
# other spellings accepted by get_task (compared lower-case)
_ALIASES: dict[str, str] = {
    "amuled/findmilk-v0": "findmilk",
    "find_milk": "findmilk",
    "amuled/driving-v0": "driving",
    "driving_and_rescuing": "driving",
}


def _load(entry_point: str) -> type[BatchedTask]:
    module, _, attr = entry_point.partition(":")
    return getattr(importlib.import_module(module), attr)


class _TaskRegistry(Mapping[str, "type[BatchedTask]"]):
    """Read-only mapping ``task name -> batched task class``, importing on first use."""

    def __getitem__(self, name: str) -> type[BatchedTask]:
        return _load(_ENTRY_POINTS[name])

    def __iter__(self) -> Iterator[str]:
        return iter(_ENTRY_POINTS)

    def __len__(self) -> int:
        return len(_ENTRY_POINTS)

    def __repr__(self) -> str:
        return f"TASKS({', '.join(_ENTRY_POINTS)})"


TASKS: Mapping[str, type[BatchedTask]] = _TaskRegistry()
"""Registry of the tasks by short name (``"findmilk"``, ``"driving"``)."""


def canonical_name(name: str) -> str:
    """Return the short task name for ``name`` (short name, alias or Gymnasium id).

    Raises:
        ValueError: Unknown task; the message lists the known ones.

    """
    if not isinstance(name, str):
        raise ScenarioError(f"name: expected a task name, got {name!r}")
    key = name.strip().lower()
    key = _ALIASES.get(key, key)
    if key not in _ENTRY_POINTS:
        raise ScenarioError(f"name: unknown task {name!r}; known tasks: {', '.join(_ENTRY_POINTS)}")
    return key


def get_task(name: str) -> type[BatchedTask]:
    """Return the batched task class named ``name`` (``"findmilk"`` or ``"driving"``).

    Gymnasium ids (``"amuled/FindMilk-v0"``) and any capitalisation are accepted too.

    Raises:
        ValueError: Unknown task.

    """
    return TASKS[canonical_name(name)]


def make_batched(name: str, num_envs: int = 1, **kwargs: Any) -> BatchedTask:
    """Create ``num_envs`` copies of the task ``name``.

    Args:
        name: Task name (see :func:`get_task`).
        num_envs: Number of copies.
        **kwargs: Constructor arguments of the task (``device``, ``seed``,
            ``shaping_coef``, ``max_steps``, task options such as ``layout``).

    Returns:
        The batched task (call ``reset()`` before stepping).

    """
    return get_task(name)(num_envs, **kwargs)


def __getattr__(attr: str) -> Any:
    if attr == "BatchedTask":
        from amuled_ma.tasks.base import BatchedTask

        return BatchedTask
    if attr == "FindMilk":
        return TASKS["findmilk"]
    if attr == "Driving":
        return TASKS["driving"]
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")
