"""``--set SECTION.KEY=VALUE``: one override of a scenario, parsed and its section checked."""

from __future__ import annotations

import tomllib
from typing import Any

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.messages import SECTIONS, did_you_mean, toml_syntax_error


def parse_set(text: str) -> tuple[str, str, Any]:
    """Parse one ``--set`` text into ``(section, key, value)``; ``KEY`` may be dotted.

    The value is read as TOML; a bare word that is not TOML is a string, but text opening a
    list or table (``[``, ``{``) must parse.

    Raises:
        ScenarioError: No ``=`` or ``.``, an unknown section, bad TOML, a value nested too deep.
    """
    key, sep, raw = text.partition("=")
    section, dot, name = key.strip().partition(".")
    if not sep or not dot or not name:
        raise ScenarioError(
            f"--set {text!r}: expected SECTION.KEY=VALUE, e.g. finetune.lambda_kl=1.0"
        )
    if section not in SECTIONS:
        raise ScenarioError(
            f"--set {text[:80]!r}: unknown section [{section}]"
            f"{did_you_mean(section, list(SECTIONS))}; the sections are "
            f"{', '.join(SECTIONS)}"
        )
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        broken = toml_syntax_error(raw)
        if broken is not None:
            raise ScenarioError(
                f"--set {key.strip()}=...: the value {raw[:60]!r} opens a TOML "
                f"{'list' if raw[0] == '[' else 'table'} but is not TOML: {broken}; write "
                f"strings in quotes and quote the whole value for the shell: --set "
                f"\"{key.strip()}=['a', 'b']\""
            ) from None
        value = raw
    except RecursionError:
        raise ScenarioError(
            f"--set {key.strip()}=...: the value is nested deeper than Python can read; "
            "give a value nested a few levels at most"
        ) from None
    return section, name, value
