"""Scenarios: everything one experiment needs, read from a TOML file and validated.

A scenario file has one table per concern (``[task]``, ``[ppo]``, ``[base]``,
``[finetune]``, ``[feedback]``, ``[evaluation]``, ``[output]``); each maps onto a frozen
pydantic v2 model (:class:`TaskConfig`, :class:`PPOConfig`, ...), and the whole file onto
:class:`Scenario`. Keys left out take defaults that follow the paper (Dubey, Dailisan,
Mahajan, "AMULED") and CleanRL's PPO.

pydantic validates every key, on load (:func:`load_scenario`, :func:`scenario_from_dict`),
on ``--set`` overrides (:meth:`Scenario.replace`) and on construction in code: types are
strict, unknown keys are refused (``extra="forbid"``), choices are ``Literal`` types and
every number has a range declared on its field (:func:`field_range` reads it back). NaN
and infinities are always refused; so are sizes whose buffers would not fit in
:data:`MEMORY_FRACTION` of the machine's memory and runs longer than :data:`MAX_ENV_STEPS`.
Each ``[feedback.agents.<name>]`` table is a typed source spec, a discriminated union on
``source`` (:mod:`amuled_ma.scenario.agents`). Any failure is one
:class:`~amuled_ma.errors.ScenarioError` line naming the file, the ``[section].key``,
what was expected and what was found (:func:`scenario_error`).

The package, one job per module (it imports no domain package):

- :mod:`~amuled_ma.scenario.sections`: the section models;
- :mod:`~amuled_ma.scenario.agents`: the agent source specs and their registry;
- :mod:`~amuled_ma.scenario.model`: :class:`Scenario`, paths resolved against its file;
- :mod:`~amuled_ma.scenario.loading`: :func:`load_scenario` and friends;
- :mod:`~amuled_ma.scenario.paths`: safe folder names, the user data folder, recordings;
- :mod:`~amuled_ma.scenario.memory`: memory estimates and the run-length cap;
- :mod:`~amuled_ma.scenario.ranges` and :mod:`~amuled_ma.scenario.messages`: declared
  ranges and error rendering.
"""

from __future__ import annotations

from amuled_ma.scenario.agents import (
    AGENT_SOURCE_KINDS,
    AGENT_SPECS,
    MORAL_AGENT,
    AgentSpec,
    EntryPointSpec,
    OllamaSpec,
    PolicySpec,
    ReplaySpec,
    RulesSpec,
    TerminalSpec,
)
from amuled_ma.scenario.loading import load_scenario, resolve_scenario_path, scenario_from_dict
from amuled_ma.scenario.memory import (
    ASSUMED_NUM_ACTIONS,
    ASSUMED_OBS_DIM,
    BYTES_PER_EPISODE,
    BYTES_PER_PARAMETER,
    BYTES_PER_TRANSITION,
    FALLBACK_MEMORY_BYTES,
    MAX_ENV_STEPS,
    MAX_SEED,
    MEMORY_FRACTION,
    physical_memory_bytes,
)
from amuled_ma.scenario.messages import BUILT_IN_CODE, scenario_error
from amuled_ma.scenario.model import Changes, Scenario, validate_section
from amuled_ma.scenario.paths import (
    MAX_NAME_LENGTH,
    NAME_RULE,
    USER_DATA_NAME,
    check_path_component,
    safe_child,
    user_data_dir,
    user_recordings_dir,
)
from amuled_ma.scenario.ranges import Range, field_length, field_range
from amuled_ma.scenario.sections import (
    PAPER_CLUSTERS,
    Activation,
    BaseConfig,
    DistillConfig,
    DistillModel,
    DistillSelection,
    EvaluationConfig,
    EvaluationMode,
    FeedbackConfig,
    FeedbackSource,
    FinetuneConfig,
    MissPolicy,
    OutputConfig,
    PPOConfig,
    Recipe,
    TaskConfig,
)

__all__ = [
    "AGENT_SOURCE_KINDS",
    "AGENT_SPECS",
    "ASSUMED_NUM_ACTIONS",
    "ASSUMED_OBS_DIM",
    "BUILT_IN_CODE",
    "BYTES_PER_EPISODE",
    "BYTES_PER_PARAMETER",
    "BYTES_PER_TRANSITION",
    "FALLBACK_MEMORY_BYTES",
    "MAX_ENV_STEPS",
    "MAX_NAME_LENGTH",
    "MAX_SEED",
    "MEMORY_FRACTION",
    "MORAL_AGENT",
    "NAME_RULE",
    "PAPER_CLUSTERS",
    "USER_DATA_NAME",
    "Activation",
    "AgentSpec",
    "BaseConfig",
    "Changes",
    "DistillConfig",
    "DistillModel",
    "DistillSelection",
    "EntryPointSpec",
    "EvaluationConfig",
    "EvaluationMode",
    "FeedbackConfig",
    "FeedbackSource",
    "FinetuneConfig",
    "MissPolicy",
    "OllamaSpec",
    "OutputConfig",
    "PPOConfig",
    "PolicySpec",
    "Range",
    "Recipe",
    "ReplaySpec",
    "RulesSpec",
    "Scenario",
    "TaskConfig",
    "TerminalSpec",
    "check_path_component",
    "field_length",
    "field_range",
    "load_scenario",
    "physical_memory_bytes",
    "resolve_scenario_path",
    "safe_child",
    "scenario_error",
    "scenario_from_dict",
    "user_data_dir",
    "user_recordings_dir",
    "validate_section",
]
