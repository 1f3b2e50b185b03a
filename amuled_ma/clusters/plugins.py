"""Code-backed agents (entry-point group ``amuled_ma.agents``); the gate for ``"module:attr"``.

Code a data file names is imported only as an installed entry point or when this run's command
line allowed it (``--allow-plugin``); docs/clusters.md.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from amuled_ma.errors import ScenarioError

#: Name of the entry-point group of code-backed agents.
ENTRY_POINT_GROUP = "amuled_ma.agents"

#: The command-line flag that allows an import path for one run.
ALLOW_FLAG = "--allow-plugin"

#: A ``"pkg.module:attr"`` import path.
IMPORT_PATH = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")

# The import paths this process's command line allowed (``--allow-plugin``).
_ALLOWED: frozenset[str] = frozenset()


def agent_entry_points() -> dict[str, EntryPoint]:
    """Every installed entry point of the ``amuled_ma.agents`` group, by name."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def set_allowed_plugins(paths: Iterable[str]) -> frozenset[str]:
    """Set the import paths this process may import (``--allow-plugin``); return the old set.

    Raises ScenarioError: a path is not ``"pkg.module:attr"``.
    """
    global _ALLOWED
    previous, paths = _ALLOWED, list(paths)
    for text in paths:
        if not isinstance(text, str) or not IMPORT_PATH.match(text):
            raise ScenarioError(
                f"{ALLOW_FLAG}: expected an import path 'pkg.module:attr' (e.g. "
                f"my_pkg.agents:MyAgent), found {text!r}"
            )
    _ALLOWED = frozenset(paths)
    return previous


def allowed_plugins() -> frozenset[str]:
    """The import paths the command line allowed (``--allow-plugin``)."""
    return _ALLOWED


def load_plugin(spec: str, what: str) -> Any:
    """Import (not call) what an entry-point name or an allowed ``"pkg.module:attr"`` names.

    Raises ScenarioError: ``spec`` (given by ``what``) is neither, or importing it failed.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ScenarioError(
            f"{what}: expected an installed {ENTRY_POINT_GROUP} entry-point name or "
            f"'pkg.module:attr', found {spec!r}"
        )
    points = agent_entry_points()
    if spec in points:
        try:
            return points[spec].load()
        except Exception as error:
            raise ScenarioError(
                f"{what}: the installed entry point {spec!r} ({points[spec].value}) failed to "
                f"load: {error!r}; fix or reinstall the package that provides it"
            ) from error
    installed = ", ".join(sorted(points)) or "none"
    if ":" not in spec:
        raise ScenarioError(
            f"{what}: no installed package registers {spec!r} in the {ENTRY_POINT_GROUP!r} "
            f"entry-point group (installed: {installed}); install the package that provides "
            f"it, or give 'pkg.module:attr' and allow it with {ALLOW_FLAG} pkg.module:attr"
        )
    installed_values = {p.value: p for p in points.values()}
    if spec not in _ALLOWED and spec not in installed_values:
        raise ScenarioError(
            f"{what}: {spec!r} is an import path, and data files may not name code to run "
            f"(nothing was imported); if you trust it, name it on this command line with "
            f"{ALLOW_FLAG} {spec} (or install it as an {ENTRY_POINT_GROUP!r} entry point; "
            f"installed: {installed})"
        )
    # the installed entry point of that value, or the one the command line named (--allow-plugin)
    point = installed_values.get(spec) or EntryPoint(name=spec, value=spec, group=ALLOW_FLAG)
    try:
        return point.load()
    except (ImportError, AttributeError) as error:
        raise ScenarioError(
            f"{what}: cannot import {spec!r}: {error}; fix the 'pkg.module:attr' string (the "
            "module must be importable from this Python environment)"
        ) from error
