"""Belief sources built by kind (`AGENT_SPECS`, entry points, `register_source`): `make_source`."""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, cast

from amuled_ma.beliefs.types import BeliefSource
from amuled_ma.errors import ScenarioError

if TYPE_CHECKING:
    from pydantic import BaseModel

Factory = Callable[..., BeliefSource]


def _importer(module: str, name: str) -> Callable[[], Factory]:
    """A function importing ``module.name`` on first use (the Ollama client and torch are heavy)."""
    return lambda: cast("Factory", getattr(importlib.import_module(module), name))


@functools.cache
def built_in() -> dict[type[BaseModel], Callable[[], Factory]]:
    """The source of each spec model of ``AGENT_SPECS``: spec model -> the function importing it."""
    from amuled_ma.scenario import agents

    here = "amuled_ma.beliefs.sources"
    return {
        agents.OllamaSpec: _importer(f"{here}.ollama", "OllamaSource"),
        agents.ReplaySpec: _importer(f"{here}.replay", "ReplaySource"),
        agents.RulesSpec: _importer(f"{here}.rules", "RulesSource"),
        agents.TerminalSpec: _importer(f"{here}.terminal", "TerminalSource"),
        agents.PolicySpec: _importer(f"{here}.policy", "PolicySource"),
        agents.EntryPointSpec: lambda: entry_point_source,
    }


_REGISTERED: dict[str, Callable[..., BeliefSource]] = {}


def register_source(kind: str, factory: Callable[..., BeliefSource]) -> None:
    """Register (or replace) ``kind`` for `make_source`; ``factory(**options)`` builds it."""
    _REGISTERED[kind] = factory


def source_kinds() -> list[str]:
    """Return every kind `make_source` knows (built-in, registered, entry points)."""
    from amuled_ma.clusters.plugins import agent_entry_points
    from amuled_ma.scenario.agents import AGENT_SPECS

    return sorted({*AGENT_SPECS, *_REGISTERED, *agent_entry_points()})


def _factory(kind: str) -> Callable[..., BeliefSource]:
    if kind in _REGISTERED:
        return _REGISTERED[kind]
    from amuled_ma.scenario.agents import AGENT_SPECS

    if kind in AGENT_SPECS:
        return built_in()[AGENT_SPECS[kind]]()
    from amuled_ma.clusters.plugins import agent_entry_points

    points = agent_entry_points()
    if kind in points:
        return points[kind].load()
    raise ScenarioError(
        f"unknown belief source kind {kind!r}; known: {', '.join(source_kinds())} "
        "(code-backed agents register under the 'amuled_ma.agents' entry-point group)"
    )


def entry_point_source(name: str, options: Mapping[str, Any] | None = None) -> BeliefSource:
    """A plug-in agent: ``name``'s factory (through `load_plugin`) called with ``options``.

    ``name``: an ``amuled_ma.agents`` entry point, or a ``"module:Class"`` allowed with
    ``--allow-plugin``. `ScenarioError`: refused, not importable or callable, or no source.
    """
    from amuled_ma.clusters.plugins import load_plugin

    factory = load_plugin(name, f"entry-point agent {name!r}")  # refuses a name that is none
    if not callable(factory):
        raise ScenarioError(
            f"entry-point agent {name!r}: it names {type(factory).__name__}, not a class or "
            "function; fix the name"
        )
    options = dict(options or {})
    try:
        source = factory(**options)
    except Exception as error:
        raise ScenarioError(
            f"entry-point agent {name!r}: building it with options {sorted(options)} "
            f"failed: {error!r}; fix its options"
        ) from error
    if not isinstance(source, BeliefSource):
        raise ScenarioError(
            f"entry-point agent {name!r} built {type(source).__name__}, expected an "
            "amuled_ma.beliefs.BeliefSource; fix the plug-in"
        )
    return source


def make_source(kind: str, **options: Any) -> BeliefSource:
    """A belief source of ``kind``; `ScenarioError` for an unknown kind or options it refuses."""
    fallback = options.get("fallback")
    if isinstance(fallback, Mapping):
        spec = dict(fallback)
        if "kind" not in spec:
            raise ScenarioError("fallback source: missing 'kind'")
        options["fallback"] = make_source(spec.pop("kind"), **spec)
    factory = _factory(kind)
    try:
        source = factory(**options)
    except TypeError as error:
        raise ScenarioError(
            f"belief source {kind!r}: bad options {sorted(options)}: {error}"
        ) from error
    if not isinstance(source, BeliefSource):
        raise ScenarioError(f"belief source {kind!r} did not build a BeliefSource: {source!r}")
    return source
