"""Task environments: FindMilk, Driving-and-Rescuing, the smart grid and entry-point tasks.

Each is a batched torch core (`BatchedTask`) with a Gymnasium view of one copy
(docs/tasks.md). Torch is imported lazily: ``import amuled_ma`` only registers the ids.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from amuled_ma.errors import ScenarioError
from amuled_ma.tasks.names import (
    ENTRY_POINT_GROUP,
    canonical_name,
    task_entry_points,
    task_names,
)

if TYPE_CHECKING:
    from amuled_ma.scenario import TaskConfig
    from amuled_ma.tasks.base import BatchedTask
    from amuled_ma.tasks.driving import Driving
    from amuled_ma.tasks.findmilk import FindMilk

__all__ = [
    "TASKS",
    "BatchedTask",
    "Driving",
    "FindMilk",
    "canonical_name",
    "get_task",
    "make_batched",
    "task_names",
]


#: Built-in task name -> the module and class of its batched core (imported at lookup: torch).
_BUILTINS: dict[str, tuple[str, str]] = {
    "findmilk": ("amuled_ma.tasks.findmilk", "FindMilk"),
    "driving": ("amuled_ma.tasks.driving", "Driving"),
    "smartgrid": ("amuled_ma.tasks.smartgrid", "SmartGrid"),
}


def _load_entry_point(name: str) -> type[BatchedTask]:
    """The class an installed ``amuled_ma.tasks`` entry point publishes, checked.

    Raises:
        ScenarioError: It fails to import, is not a `BatchedTask` subclass, or its ``name``
            differs from the entry point's.
    """
    from amuled_ma.tasks.base import BatchedTask

    point = task_entry_points()[name]
    head = f"task {name!r}: the installed {ENTRY_POINT_GROUP} entry point {point.value!r}"
    try:
        cls = point.load()
    except Exception as error:
        raise ScenarioError(
            f"{head} failed to import: {error!r}; fix or reinstall the package providing it"
        ) from error
    if not (isinstance(cls, type) and issubclass(cls, BatchedTask)):
        raise ScenarioError(
            f"{head} is {cls!r}, expected a subclass of amuled_ma.tasks.BatchedTask; "
            "publish the task class itself"
        )
    if getattr(cls, "name", None) != name:
        raise ScenarioError(
            f"{head} is a class named {getattr(cls, 'name', None)!r}, expected name = "
            f"{name!r}; give the class the entry point's name"
        )
    return cls


class _TaskRegistry(Mapping[str, "type[BatchedTask]"]):
    """Read-only ``task name -> class``: built-ins, then entry points (read at each lookup)."""

    def __getitem__(self, name: str) -> type[BatchedTask]:
        if name in _BUILTINS:
            module, cls = _BUILTINS[name]
            return getattr(importlib.import_module(module), cls)
        if name in task_entry_points():
            return _load_entry_point(name)
        raise KeyError(name)

    def __iter__(self) -> Iterator[str]:
        return iter(task_names())

    def __len__(self) -> int:
        return len(task_names())

    def __repr__(self) -> str:
        return f"TASKS({', '.join(task_names())})"


TASKS: Mapping[str, type[BatchedTask]] = _TaskRegistry()
"""Registry of the tasks by short name (built-in, then entry points)."""


def get_task(name: str) -> type[BatchedTask]:
    """Return the batched task class of a short name, alias or Gymnasium id (any case).

    Raises:
        ScenarioError: Unknown task (a ``ValueError``), or an entry point that does not
            load a task class.
    """
    return TASKS[canonical_name(name)]


def make_batched(name: str, num_envs: int = 1, **kwargs: Any) -> BatchedTask:
    """Create ``num_envs`` copies of the task ``name`` (call ``reset()`` before stepping)."""
    return get_task(name)(num_envs, **kwargs)


def make_task(task: TaskConfig, num_envs: int, *, shaping_coef: float, seed: int) -> BatchedTask:
    """Create ``num_envs`` copies of the ``[task]`` section's task on the CPU, seeded ``seed``.

    ``shaping_coef`` is ``c`` of the reward ``r_env + c * r_shaping``; the section refused
    reserved options on load.

    Raises:
        ScenarioError: The task refuses an option (one without an option model).
    """
    kwargs: dict[str, Any] = dict(task.options)
    if task.max_steps:
        kwargs["max_steps"] = task.max_steps
    try:
        return make_batched(
            task.name, num_envs, device="cpu", seed=seed, shaping_coef=shaping_coef, **kwargs
        )
    except (TypeError, ValueError) as error:
        # a task refuses an unknown or invalid option: one line naming the key
        shown = ", ".join(f"{k}={v!r}" for k, v in task.options.items()) or "none"
        raise ScenarioError(
            f"key [task].options of task {task.name!r} ({shown}): {error}; see "
            "docs/tasks.md for the options of each task"
        ) from None


def __getattr__(attr: str) -> Any:
    if attr == "BatchedTask":
        from amuled_ma.tasks.base import BatchedTask

        return BatchedTask
    if attr in ("FindMilk", "Driving"):
        return TASKS[attr.lower()]
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")
