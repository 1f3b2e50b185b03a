"""Loading a scenario: a shipped name or a TOML file, parsed and validated."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any

from amuled_ma.errors import ScenarioError
from amuled_ma.files.resources import read_text, scenarios_dir
from amuled_ma.scenario.messages import did_you_mean, unknown_top_level
from amuled_ma.scenario.model import Scenario
from amuled_ma.scenario.panel_weights import weights_prior
from amuled_ma.scenario.paths import check_path_component
from amuled_ma.scenario.sections import validate_model


def scenario_from_dict(data: dict[str, Any], *, path: Path | None = None) -> Scenario:
    """Build and validate a `Scenario` from parsed TOML data (``path``: its file, for errors)."""
    source = str(path) if path is not None else "<scenario>"
    if "path" in data:  # a field of Scenario, but never a key of a scenario file
        raise ScenarioError(unknown_top_level("path", source))
    values = dict(data)
    if "name" not in values:
        stem = path.stem if path is not None else "scenario"
        values["name"] = check_path_component(
            stem, f"{source}: the scenario name (the file name, as no top-level name is set)"
        )
    return validate_model(Scenario, {**values, "path": path}, source)


def resolve_scenario_path(name_or_path: str | os.PathLike[str]) -> Path:
    """The absolute path of a scenario file or a shipped scenario's name (else `ScenarioError`)."""
    path = Path(name_or_path).expanduser()
    if path.is_file():
        return path.resolve()
    shipped = scenarios_dir()
    for candidate in (shipped / str(name_or_path), shipped / f"{name_or_path}.toml"):
        if candidate.is_file():
            return candidate.resolve()
    names = sorted(p.stem for p in shipped.glob("*.toml"))
    available = ", ".join(names)
    raise ScenarioError(
        f"scenario {str(name_or_path)!r} not found: not a file, and not a shipped scenario "
        f"(shipped: {available or 'none'} in {shipped}){did_you_mean(str(name_or_path), names)}"
    )


def load_scenario(name_or_path: str | os.PathLike[str]) -> Scenario:
    """Load and validate a scenario from a TOML file or a shipped scenario's name.

    Raises:
        ScenarioError: The file is missing, not valid TOML, fails validation, or its
            ``[feedback].weights`` file is bad.
    """
    path = resolve_scenario_path(name_or_path)
    text = read_text(path, "scenario", ScenarioError, max_bytes=MAX_SCENARIO_BYTES)
    data = parse_toml(text, path, "scenario", ScenarioError, MAX_SCENARIO_CHARS)
    try:
        scenario = scenario_from_dict(data, path=path)
    except RecursionError:
        raise ScenarioError(_too_deep(path, None, "scenario")) from None
    feedback = scenario.feedback
    if feedback.weights.strip():
        weights_prior(feedback.weights, feedback.clusters, scenario.resolve, str(path))
    return scenario


#: Most characters a scenario file may hold (a shipped one holds about 10,000).
MAX_SCENARIO_CHARS = 1_000_000
#: Largest scenario file read [bytes]: UTF-8 holds a character in at most 4 bytes, so no
#: file within `MAX_SCENARIO_CHARS` is refused by its size, and a 2 GB file is
#: refused before it is read.
MAX_SCENARIO_BYTES = 4 * MAX_SCENARIO_CHARS
#: Most levels of ``[`` / ``{`` nesting a scenario value may have.
MAX_TOML_DEPTH = 32


def nesting_depth(text: str) -> int:
    """The deepest ``[``/``{`` nesting of TOML text outside strings (rough, linear)."""
    depth = deepest = 0
    quote = ""
    i, n = 0, len(text)
    while i < n:
        char = text[i]
        if quote:
            if char == "\\" and quote == '"':
                i += 2
                continue
            if text.startswith(quote, i):
                i += len(quote)
                quote = ""
                continue
        elif char == "#":
            end = text.find("\n", i)
            i = n if end < 0 else end
            continue
        elif char in "\"'":
            quote = char * 3 if text.startswith(char * 3, i) else char
            i += len(quote)
            continue
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth = max(0, depth - 1)
        i += 1
    return deepest


def parse_toml(
    text: str, path: Path, what: str, error_class: type[Exception], max_chars: int
) -> dict[str, Any]:
    """Parse a TOML file's text, refusing a file too long or nested too deep.

    Raises:
        Exception: ``error_class``: longer than ``max_chars``, nested deeper than
            `MAX_TOML_DEPTH`, or not valid TOML.
    """
    if len(text) > max_chars:
        raise error_class(
            f"{path}: the {what} is {len(text):,} characters long, more than the "
            f"{max_chars:,} a {what} may be; is it the right file?"
        )
    depth = nesting_depth(text)
    if depth > MAX_TOML_DEPTH:
        raise error_class(_too_deep(path, depth, what))
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise error_class(f"{path}: not valid TOML: {error}") from None
    except RecursionError:  # nesting the bracket count above did not see (dotted keys)
        raise error_class(_too_deep(path, None, what)) from None


def _too_deep(path: Path, depth: int | None, what: str) -> str:
    found = f"{depth} levels" if depth is not None else "deeper than Python can read"
    return (
        f"{path}: the {what} nests values {found}; a {what} nests at most "
        f"{MAX_TOML_DEPTH} levels of [ ] and {{ }} (is it the right file?)"
    )
