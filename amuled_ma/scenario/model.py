"""The whole scenario (`Scenario`): its sections, its paths, its overrides."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.messages import SECTIONS, did_you_mean, unknown_section
from amuled_ma.scenario.paths import check_path_component, find_recording, safe_child
from amuled_ma.scenario.sections import (
    BaseConfig,
    EvaluationConfig,
    FeedbackConfig,
    FinetuneConfig,
    OutputConfig,
    PPOConfig,
    TaskConfig,
    _init,
    _source,
    validate_model,
)

#: Changes to a scenario: ``(section, {key: value})`` pairs, applied in order
#: (:meth:`Scenario.changed`).
Changes = tuple[tuple[str, dict[str, Any]], ...]


class Scenario(BaseModel):
    """A whole experiment setup: one section model per table, plus ``name`` and ``path``.

    Built in code it is validated like a file (`ScenarioError`); ``model_copy(update=...)``
    copies without validating, `replace` validates. ``name`` is one safe path component.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    name: str = "scenario"
    path: Path | None = None
    task: TaskConfig = Field(default_factory=TaskConfig)
    ppo: PPOConfig = Field(default_factory=PPOConfig)
    base: BaseConfig = Field(default_factory=BaseConfig)
    finetune: FinetuneConfig = Field(default_factory=FinetuneConfig)
    feedback: FeedbackConfig = Field(default_factory=FeedbackConfig)
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)

    def __init__(self, /, **data: object) -> None:
        _init(self, data, ())

    @field_validator("name")
    @classmethod
    def _name_is_a_folder_name(cls, value: str, info: ValidationInfo) -> str:
        return check_path_component(value, f"{_source(info)}: key name")

    @property
    def base_dir(self) -> Path:
        """Folder that relative paths of this scenario are resolved against."""
        return self.path.parent if self.path is not None else Path.cwd()

    def resolve(self, value: str) -> Path:
        """Resolve a path from this scenario against its folder."""
        path = Path(os.path.expandvars(os.path.expanduser(value)))
        return path if path.is_absolute() else (self.base_dir / path).resolve()

    def store_path(self, run_dir: Path | None = None) -> Path:
        """The belief store file; a relative path is against the run folder (else this file's)."""
        path = Path(self.feedback.store)
        return path if path.is_absolute() else (run_dir or self.base_dir) / path

    def recording_path(self, *, required: bool = False) -> Path:
        """Find the replayed recording ``[feedback].recording``, by path or by bare name.

        First existing wins: the value relative to the scenario file; ``$AMULED_RECORDINGS``;
        `user_recordings_dir`; ``../shared/amuled-recordings`` beside the repository checkout.
        Not found: ``required`` raises `ScenarioError` (every place looked), else the value.
        """
        return find_recording(
            self.feedback.recording,
            self.resolve,
            where=str(self.path or f"scenario {self.name!r}"),
            required=required,
        )

    def to_dict(self) -> dict[str, Any]:
        """The fully resolved scenario as plain data (``config.json``; `scenario_from_dict`)."""
        data = self.model_dump()
        data["path"] = str(self.path) if self.path else None
        return data

    def settings(self) -> dict[str, Any]:
        """The validated settings as JSON ``{section: {key: value}}``, for comparing scenarios.

        ``name`` and ``path`` are left out (where a scenario lives, not what a run learns); paths
        inside sections are kept as written. Equal ``settings()`` train and evaluate alike.
        """
        return self.model_dump(mode="json", exclude={"name", "path"})

    def replace(self, section: str, **changes: object) -> Scenario:
        """A copy with some keys of one section changed, validated like a file (`ScenarioError`)."""
        source = f"{self.path or self.name} (override of [{section}])"
        if section not in SECTIONS:
            raise ScenarioError(unknown_section(section, source))
        merged: dict[str, Any] = dict(getattr(self, section))
        for key, value in changes.items():
            head, dot, _ = key.partition(".")
            if dot and not isinstance(merged.get(head), BaseModel | dict):
                close = did_you_mean(head, list(merged))
                where = (
                    f"[{section}].{head} is not a table"
                    if head in merged
                    else f"no key [{section}].{head}{close}"
                )
                raise ScenarioError(f"{source}: key [{section}].{key}: {where}")
            merged = _with_nested(merged, key, value)
        return self.model_copy(update={section: validate_section(section, merged, source)})

    def changed(self, changes: Changes) -> Scenario:
        """Return a copy with each ``(section, {key: value})`` applied in order (`replace`)."""
        scenario = self
        for section, values in changes:
            scenario = scenario.replace(section, **values)
        return scenario

    def default_run_dir(self, runs_dir: str | os.PathLike[str] | None = None) -> Path:
        """``<runs_dir>/<name>``, directly inside ``runs_dir`` (an unsafe name: `ScenarioError`)."""
        root = self.output.runs_dir if runs_dir is None else runs_dir
        return safe_child(root, self.name, what=f"{self.path or '<scenario>'}: key name")


def _with_nested(table: BaseModel | dict[str, Any], key: str, value: object) -> dict[str, Any]:
    """A table's keys as a dict, with ``key`` (dotted for nested tables) set."""
    data = dict(table)
    head, dot, rest = key.partition(".")
    if dot and isinstance(data.get(head), BaseModel | dict):
        data[head] = _with_nested(data[head], rest, value)
    else:
        data[key] = value
    return data


def validate_section(section: str, values: dict[str, Any], source: str) -> BaseModel:
    """Validate one section's values as a file's table is validated, and build its model.

    Raises:
        ScenarioError: An unknown section or key, or a bad value; names file, key and fix.
    """
    model = SECTIONS.get(section)
    if model is None:
        raise ScenarioError(unknown_section(section, source))
    return validate_model(model, values, source, (section,))
