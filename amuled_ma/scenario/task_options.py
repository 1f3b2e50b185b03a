"""``[task].options``: each task's keyword options, checked when the scenario is read.

A task refuses a bad option only when built, after the run folder exists, so the scenario
checks them first against one model per task (`TASK_OPTIONS`, held equal to the constructors).
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
    """Options of FindMilk: ``layout`` (``"paper"`` or ``"random"`` each episode), ``tie_break``.

    ``tie_break``: which of several equally near babies the observation shows, ``"first"``
    (smallest ``(x, y)``) or ``"random"`` (the authors' environment).
    """

    layout: Literal["paper", "random"] = "paper"
    tie_break: Literal["first", "random"] = "first"


class DrivingOptions(_Options):
    """Options of Driving: per-step chances of a car (paper 0.16) and a grandma (paper 0.09)."""

    p_car: float = Field(0.16, ge=0, le=1, description="a probability per step")
    p_grandma: float = Field(0.09, ge=0, le=1, description="a probability per step")


class SmartGridOptions(_Options):
    """Options of the smart grid: households (the learner first) and offices (OpenEI profiles)."""

    households: int = Field(3, ge=1, le=1000, description="a count of prosumers")
    offices: int = Field(1, ge=0, le=1000, description="a count of prosumers")


#: The option model of each built-in task, by its short name (an entry-point task checks
#: its own options when it is built).
TASK_OPTIONS: dict[str, type[_Options]] = {
    "findmilk": FindMilkOptions,
    "driving": DrivingOptions,
    "smartgrid": SmartGridOptions,
}
#: Other spellings of a task name (compared lower-case) -> its short name.
ALIASES: dict[str, str] = {
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
    return TASK_OPTIONS.get(ALIASES.get(key, key))


def check_task_options(task: str, options: Mapping[str, Any], where: str) -> None:
    """Refuse ``[task].options`` the task would refuse (a task without a model: left to it).

    Raises:
        ScenarioError: An option the run sets itself, an unknown option, or a bad value.
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
            f"{', '.join(model.model_fields) or 'none'} (docs/tasks.md)"
        ) from None
