"""``[task].options``: each task's keyword options, checked when the scenario is read.

A task takes its own options (FindMilk ``layout``, Driving ``p_car``); the task refuses a
bad one when it is built, which is after the run folder exists and Ray has started. So the
scenario checks them first, against one model per task (:data:`TASK_OPTIONS`): a bad
value, an unknown option, or an option the run sets itself (:data:`RESERVED`) is one line
naming ``[task].options`` before any folder is made. The models mirror the tasks'
constructors (``amuled_ma.tasks``); ``tests/test_task_options.py`` holds them equal
(names, defaults, accepted values), so a new option of a task must be declared here too.

This module imports no domain package (the scenario layer describes; the tasks sit above).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from amuled_ma.errors import ScenarioError

#: Keyword arguments of a task that the run sets ([task].seed, [task].max_steps, the
#: reward's shaping, the device): never a task option.
RESERVED = ("device", "seed", "shaping_coef", "max_steps")


class _Options(BaseModel):
    """Base of the option models: strict types, no unknown option, no NaN."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class FindMilkOptions(_Options):
    """Options of FindMilk (``amuled_ma.tasks.findmilk.FindMilk``).

    Attributes:
        layout: ``"paper"`` (the paper's fixed layout) or ``"random"`` (every episode).
        tie_break: Which of several equally near babies the observation shows:
            ``"first"`` (smallest ``(x, y)``) or ``"random"`` (the authors' environment).

    """

    layout: Literal["paper", "random"] = "paper"
    tie_break: Literal["first", "random"] = "first"


class DrivingOptions(_Options):
    """Options of Driving-and-Rescuing (``amuled_ma.tasks.driving.Driving``).

    Attributes:
        p_car: Probability that a car appears on a step (paper: 0.16).
        p_grandma: Probability that a grandma appears on a step (paper: 0.09).

    """

    p_car: float = Field(0.16, ge=0, le=1, description="a probability per step")
    p_grandma: float = Field(0.09, ge=0, le=1, description="a probability per step")


class SmartGridOptions(_Options):
    """Options of the smart grid (``amuled_ma.tasks.smartgrid.SmartGrid``).

    Attributes:
        households: Households of the grid, the learner first (OpenEI daily profile).
        offices: Offices of the grid (OpenEI daily profile).

    """

    households: int = Field(3, ge=1, le=1000, description="a count of prosumers")
    offices: int = Field(1, ge=0, le=1000, description="a count of prosumers")


#: The option model of each built-in task, by its short name (an entry-point task checks
#: its own options when it is built).
TASK_OPTIONS: dict[str, type[_Options]] = {
    "findmilk": FindMilkOptions,
    "driving": DrivingOptions,
    "smartgrid": SmartGridOptions,
}
#: Other spellings of a task name (``amuled_ma.tasks.names.ALIASES``, compared lower-case).
_ALIASES = {
    "amuled/findmilk-v0": "findmilk",
    "find_milk": "findmilk",
    "amuled/driving-v0": "driving",
    "driving_and_rescuing": "driving",
    "smart_grid": "smartgrid",
    "ethical-smart-grid": "smartgrid",
}


def options_model(task: str) -> type[_Options] | None:
    """The option model of the task named ``task`` (short name, alias, any case), or None."""
    key = task.strip().lower()
    return TASK_OPTIONS.get(_ALIASES.get(key, key))


def _accepted(model: type[_Options]) -> str:
    """``layout, tie_break`` for a task's options, or ``none`` for a task without any."""
    return ", ".join(model.model_fields) or "none"


def check_task_options(task: str, options: Mapping[str, Any], where: str) -> None:
    """Refuse ``[task].options`` the task would refuse, in one line naming the key.

    Args:
        task: ``[task].name``.
        options: ``[task].options``.
        where: The scenario file (or ``--set`` override), named first in the message.

    Raises:
        ScenarioError: An option the run sets itself, an unknown option, or a value the
            task does not accept; the message names the option, what the task accepts and
            what was found. A task without a model here is left to the task itself.

    """
    head = f"{where}: key [task].options"
    reserved = sorted(set(options) & set(RESERVED))
    if reserved:
        raise ScenarioError(
            f"{head}: {', '.join(reserved)} cannot be a task option (it is set by the run: "
            "[task].seed, [task].max_steps, the reward's shaping); remove it"
        )
    model = options_model(task)
    if model is None:
        return
    try:
        model.model_validate(dict(options))
    except ValidationError as error:
        first = error.errors(include_url=False)[0]
        name = ".".join(map(str, first["loc"]))
        if first["type"] == "extra_forbidden":
            problem = f"unknown option {name!r}"
        else:
            said = first["msg"].removeprefix("Input ")
            problem = f"option {name} {said}, found {first.get('input')!r}"
        raise ScenarioError(
            f"{head} of task {task!r}: {problem}; the task's options are "
            f"{_accepted(model)} (docs/tasks.md)"
        ) from None
