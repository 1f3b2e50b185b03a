"""Loading a scenario: a shipped name or a TOML file, parsed and validated."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any

from amuled_ma.errors import ScenarioError
from amuled_ma.resources import read_text, scenarios_dir
from amuled_ma.scenario.messages import unknown_top_level
from amuled_ma.scenario.model import Scenario
from amuled_ma.scenario.paths import check_path_component
from amuled_ma.scenario.sections import _validate


def scenario_from_dict(data: dict[str, Any], *, path: Path | None = None) -> Scenario:
    """Build and validate a :class:`Scenario` from parsed TOML data.

    Args:
        data: The parsed TOML document (or :meth:`Scenario.to_dict` without ``path``).
        path: The file it came from (used in errors and to resolve relative paths).

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: Unknown section or key, a value of the wrong type or out of its
            range (see :func:`field_range`), or a name that is no safe folder name.

    """
    source = str(path) if path is not None else "<scenario>"
    if "path" in data:  # a field of Scenario, but never a key of a scenario file
        raise ScenarioError(unknown_top_level("path", source))
    values = dict(data)
    if "name" not in values:
        stem = path.stem if path is not None else "scenario"
        values["name"] = check_path_component(
            stem, f"{source}: the scenario name (the file name, as no top-level name is set)"
        )
    return _validate(Scenario, {**values, "path": path}, source)


def resolve_scenario_path(name_or_path: str | os.PathLike[str]) -> Path:
    """Find a scenario file from a path or the name of a shipped scenario.

    Args:
        name_or_path: A path to a TOML file, or a shipped scenario's name (``findmilk``).

    Returns:
        The absolute path of the file.

    Raises:
        ScenarioError: Neither an existing file nor a shipped scenario.

    """
    path = Path(name_or_path).expanduser()
    if path.is_file():
        return path.resolve()
    shipped = scenarios_dir()
    for candidate in (shipped / str(name_or_path), shipped / f"{name_or_path}.toml"):
        if candidate.is_file():
            return candidate.resolve()
    available = ", ".join(sorted(p.stem for p in shipped.glob("*.toml")))
    raise ScenarioError(
        f"scenario {str(name_or_path)!r} not found: not a file, and not a shipped scenario "
        f"(shipped: {available or 'none'} in {shipped})"
    )


def load_scenario(name_or_path: str | os.PathLike[str]) -> Scenario:
    """Load and validate a scenario from a TOML file or a shipped scenario's name.

    Args:
        name_or_path: File path or shipped name (``findmilk``, ``driving``).

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: The file is missing, is not valid TOML, or fails validation.

    """
    path = resolve_scenario_path(name_or_path)
    try:
        data = tomllib.loads(read_text(path, "scenario", ScenarioError))
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{path}: not valid TOML: {error}") from None
    return scenario_from_dict(data, path=path)
