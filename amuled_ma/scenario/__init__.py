"""Scenarios: everything one experiment needs, read from a TOML file and validated.

One frozen pydantic model per table, the whole file a `Scenario`; defaults follow the paper
and CleanRL's PPO. Validation runs on load, on ``--set`` and in code; any failure is one
`ScenarioError` line. The package imports no domain package.
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
