"""A registry of belief-source kinds: ``make_source(kind, **options)``.

Built-in kinds: ``"ollama"`` (:class:`~amuled_ma.beliefs.ollama.OllamaSource`),
``"replay"`` (:class:`~amuled_ma.beliefs.replay.ReplaySource`), ``"rules"``
(:class:`~amuled_ma.beliefs.rules.RulesSource`) and ``"scripted"``
(:class:`~amuled_ma.beliefs.rules.ScriptedSource`). Other kinds are looked up in the
``amuled_ma.agents`` entry-point group (code-backed agents shipped by other packages),
or added at run time with :func:`register_source`.

Options are the source class's keyword arguments. A ``fallback`` option given as a
mapping ``{"kind": ..., ...}`` is itself built with :func:`make_source`, so a scenario
can say ``fallback = { kind = "ollama", model = "amuled-tiny" }``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

from amuled_ma.beliefs.types import BeliefSource
from amuled_ma.errors import ScenarioError

_BUILTIN: dict[str, str] = {
    "ollama": "amuled_ma.beliefs.ollama:OllamaSource",
    "replay": "amuled_ma.beliefs.replay:ReplaySource",
    "rules": "amuled_ma.beliefs.rules:RulesSource",
    "scripted": "amuled_ma.beliefs.rules:ScriptedSource",
}
_REGISTERED: dict[str, Callable[..., BeliefSource]] = {}


def register_source(kind: str, factory: Callable[..., BeliefSource]) -> None:
    """Register (or replace) a source kind at run time.

    Args:
        kind: The name used with :func:`make_source`.
        factory: Called with the options; returns a :class:`BeliefSource`.

    """
    _REGISTERED[kind] = factory


def source_kinds() -> list[str]:
    """Return every kind :func:`make_source` knows (built-in, registered, entry points)."""
    from amuled_ma.clusters.plugins import agent_entry_points

    return sorted({*_BUILTIN, *_REGISTERED, *agent_entry_points()})


def _factory(kind: str) -> Callable[..., BeliefSource]:
    if kind in _REGISTERED:
        return _REGISTERED[kind]
    if kind in _BUILTIN:
        module, _, attr = _BUILTIN[kind].partition(":")
        return getattr(importlib.import_module(module), attr)
    from amuled_ma.clusters.plugins import agent_entry_points

    points = agent_entry_points()
    if kind in points:
        return points[kind].load()
    raise ScenarioError(
        f"unknown belief source kind {kind!r}; known: {', '.join(source_kinds())} "
        "(code-backed agents register under the 'amuled_ma.agents' entry-point group)"
    )


def make_source(kind: str, **options: Any) -> BeliefSource:
    """Build a belief source by kind.

    Args:
        kind: ``"ollama"``, ``"replay"``, ``"rules"``, ``"scripted"``, a registered
            kind, or an ``amuled_ma.agents`` entry-point name.
        **options: The source's keyword arguments.

    Returns:
        The source.

    Raises:
        ScenarioError: Unknown kind, or options the source does not accept.

    """
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
