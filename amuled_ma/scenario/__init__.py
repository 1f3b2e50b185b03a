"""Scenarios: everything one experiment needs, read from a TOML file and validated.

One frozen pydantic model per table (defaults: the paper's, CleanRL's PPO), the whole file a
`Scenario`; any failure, on load, on ``--set`` or in code, is one `ScenarioError` line.
"""

from __future__ import annotations

from amuled_ma.scenario.agents import AGENT_SPECS, MORAL_AGENT, OllamaSpec, TerminalSpec
from amuled_ma.scenario.loading import load_scenario, resolve_scenario_path, scenario_from_dict
from amuled_ma.scenario.model import Changes, Scenario, validate_section
from amuled_ma.scenario.paths import (
    check_path_component,
    safe_child,
    user_data_dir,
    user_recordings_dir,
)
from amuled_ma.scenario.ranges import field_length, field_range
from amuled_ma.scenario.sections import (
    PAPER_CLUSTERS,
    BaseConfig,
    DistillConfig,
    EvaluationConfig,
    FeedbackConfig,
    FinetuneConfig,
    OutputConfig,
    PPOConfig,
    TaskConfig,
)

__all__ = [
    "AGENT_SPECS",
    "MORAL_AGENT",
    "PAPER_CLUSTERS",
    "BaseConfig",
    "Changes",
    "DistillConfig",
    "EvaluationConfig",
    "FeedbackConfig",
    "FinetuneConfig",
    "OllamaSpec",
    "OutputConfig",
    "PPOConfig",
    "Scenario",
    "TaskConfig",
    "TerminalSpec",
    "check_path_component",
    "field_length",
    "field_range",
    "load_scenario",
    "resolve_scenario_path",
    "safe_child",
    "scenario_from_dict",
    "user_data_dir",
    "user_recordings_dir",
    "validate_section",
]
