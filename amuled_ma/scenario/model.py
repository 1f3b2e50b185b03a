"""The whole scenario (:class:`Scenario`): its sections, its paths, its overrides."""

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
    """A whole experiment setup.

    Built in code (``Scenario(name="x")``) it is validated like a file; a failure raises
    :class:`~amuled_ma.errors.ScenarioError`. ``model_copy(update=...)`` copies without
    validating; :meth:`replace` validates.

    Attributes:
        name: Scenario name (the file stem unless ``name`` is set at top level); it names
            the run folder, so it must be one safe path component (:data:`NAME_RULE`).
        path: The file it was loaded from (None when built in code).
        task: See :class:`TaskConfig`.
        ppo: See :class:`PPOConfig`.
        base: See :class:`BaseConfig`.
        finetune: See :class:`FinetuneConfig`.
        feedback: See :class:`FeedbackConfig`.
        evaluation: See :class:`EvaluationConfig`.
        output: See :class:`OutputConfig`.

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
        """The belief store file of a run: ``[feedback].store``.

        A relative path is resolved against the run folder (or this scenario's folder
        without one).
        """
        path = Path(self.feedback.store)
        return path if path.is_absolute() else (run_dir or self.base_dir) / path

    def recording_path(self, *, required: bool = False) -> Path:
        """Find the replayed recording ``[feedback].recording``, by path or by name.

        ``recording`` is a path (``"../data/findmilk-gpt-4o-mini.json"``) or a bare name
        (``"findmilk-gpt-4o-mini"``, ``.json`` optional). Each place is searched for its file
        name, then (unless it ends in ``.json``) that name with ``.json`` added. The first
        existing file wins:

        1. the value as given, relative to the scenario file;
        2. ``$AMULED_RECORDINGS/<name>.json``;
        3. the user data folder, :func:`user_recordings_dir` (where
           ``amuled import authors PATH`` writes);
        4. ``../shared/amuled-recordings/<name>.json`` beside the repository checkout
           (the nearest folder with ``.git``) that holds the current directory.

        Args:
            required: Raise when no place holds the file. Without it the value as given
                (resolved) is returned, as before this lookup existed, so callers that
                test ``.exists()`` keep working.

        Returns:
            The recording file.

        Raises:
            ScenarioError: ``required`` and nothing was found (or the value is empty); the
                message lists every place looked and names ``amuled import authors PATH``.

        """
        return find_recording(
            self.feedback.recording,
            self.resolve,
            where=str(self.path or f"scenario {self.name!r}"),
            required=required,
        )

    def to_dict(self) -> dict[str, Any]:
        """Return the fully resolved scenario as plain data (for ``config.json``).

        Every section's keys (defaults filled in), the ``name`` and the ``path`` (a string,
        or None). :func:`scenario_from_dict` builds the scenario back from it once ``path``
        is taken out.
        """
        data = self.model_dump()
        data["path"] = str(self.path) if self.path else None
        return data

    def settings(self) -> dict[str, Any]:
        """Return the validated settings as plain JSON data, for comparing two scenarios.

        ``{section: {key: value}}`` for the seven sections (``task``, ``ppo``, ``base``,
        ``finetune``, ``feedback``, ``evaluation``, ``output``), every key present with
        defaults filled in, values as JSON types (``model_dump(mode="json")``: lists, not
        tuples; floats stay floats, so ``lambda_kl = 3`` and ``3.0`` compare equal). Left
        out: ``name`` and ``path``, which say where a scenario lives and where its runs go,
        not what a run learns. Paths inside the sections (``recording``, ``store``,
        ``runs_dir``) are kept as written, not resolved. Two scenarios with equal
        ``settings()`` train and evaluate alike; a resume check compares the saved
        ``settings()`` (or the part of it a variant depends on) with the current one.

        Returns:
            A new dict of JSON-serialisable data (``json.dumps`` takes it as it is).

        """
        return self.model_dump(mode="json", exclude={"name", "path"})

    def replace(self, section: str, **changes: object) -> Scenario:
        """Return a copy with some keys of one section changed, validated like a file.

        Args:
            section: The section (``"finetune"``).
            **changes: New values by key (``lambda_kl=1.0``).

        Returns:
            The new scenario; this one is unchanged.

        Raises:
            ScenarioError: An unknown section or key, or a value of the wrong type or out of
                its range; the message names ``<file> (override of [section])``.

        """
        source = f"{self.path or self.name} (override of [{section}])"
        model = SECTIONS.get(section)
        if model is None:
            raise ScenarioError(unknown_section(section, source))
        current = getattr(self, section)
        merged = {key: getattr(current, key) for key in type(current).model_fields}
        for key, value in changes.items():
            head, dot, rest = key.partition(".")
            if not dot:
                merged[key] = value
                continue
            table = merged.get(head)
            if not isinstance(table, BaseModel | dict):
                close = did_you_mean(head, list(merged))
                where = (
                    f"[{section}].{head} is not a table"
                    if head in merged
                    else f"no key [{section}].{head}{close}"
                )
                raise ScenarioError(f"{source}: key [{section}].{key}: {where}")
            merged[head] = _with_nested(table, rest, value)
        new_section = validate_model(model, merged, source, (section,))
        return self.model_copy(update={section: new_section})

    def changed(self, changes: Changes) -> Scenario:
        """Return a copy with each ``(section, {key: value})`` applied in order (:meth:`replace`).

        Raises:
            ScenarioError: As :meth:`replace`.

        """
        scenario = self
        for section, values in changes:
            scenario = scenario.replace(section, **values)
        return scenario

    def default_run_dir(self, runs_dir: str | os.PathLike[str] | None = None) -> Path:
        """Return ``<runs_dir>/<name>``, guaranteed to lie directly inside ``runs_dir``.

        Args:
            runs_dir: The folder of runs (default: ``[output].runs_dir``, relative to the
                current directory as before).

        Returns:
            The run directory, relative when ``runs_dir`` is.

        Raises:
            ScenarioError: The name is not a safe path component (see :func:`safe_child`).

        """
        root = self.output.runs_dir if runs_dir is None else runs_dir
        return safe_child(root, self.name, what=f"{self.path or '<scenario>'}: key name")


def _with_nested(table: BaseModel | dict[str, Any], key: str, value: object) -> dict[str, Any]:
    """A nested table's keys as a dict, with ``key`` (dotted for deeper tables) set."""
    data = (
        {k: getattr(table, k) for k in type(table).model_fields}
        if isinstance(table, BaseModel)
        else dict(table)
    )
    head, dot, rest = key.partition(".")
    if dot and isinstance(data.get(head), BaseModel | dict):
        data[head] = _with_nested(data[head], rest, value)
    else:
        data[key] = value
    return data


def validate_section(section: str, values: dict[str, Any], source: str) -> BaseModel:
    """Validate one section's values as a file's table is validated, and build it.

    Types, choices, the declared ranges (:func:`field_range`), safe names, finite floats
    (also inside free tables), the memory estimates and the run-length cap: everything
    the section model checks.

    Args:
        section: Section name (``ppo``).
        values: Keys of the section, by name (keys left out take their defaults).
        source: The file (or ``--set`` override) the values came from, for errors.

    Returns:
        The section model (:class:`PPOConfig` for ``ppo``).

    Raises:
        ScenarioError: An unknown section or key, or a value of the wrong type or out of
            range; the message names the file, the ``[section].key``, what was expected
            (the range and why) and the value found.

    """
    model = SECTIONS.get(section)
    if model is None:
        raise ScenarioError(unknown_section(section, source))
    return validate_model(model, values, source, (section,))
