"""`RoutedSource`: one batch split across the members' sources (``docs/beliefs.md``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, ask, in_order
from amuled_ma.errors import ScenarioError


class RoutedSource(BeliefSource):
    """Answer each request with the source of its agent (``request.cluster``).

    ``routes``: ``{agent: source}`` (one source may serve several agents, in one call);
    ``default``: the source of every other agent. `ValueError`: neither is given.
    """

    name = "routed"

    def __init__(
        self, routes: Mapping[str, BeliefSource], default: BeliefSource | None = None
    ) -> None:
        if not routes and default is None:
            raise ValueError("a routed source needs at least one route or a default source")
        self.routes: dict[str, BeliefSource] = dict(routes)
        self.default = default
        members: dict[int, tuple[BeliefSource, list[str]]] = {}
        for agent, source in self.routes.items():
            members.setdefault(id(source), (source, []))[1].append(agent)
        if default is not None:
            members.setdefault(id(default), (default, []))
        #: The distinct member sources, each with the agents routed to it (the default
        #: source's list holds only agents named in ``routes``).
        self.members: list[tuple[BeliefSource, tuple[str, ...]]] = [
            (source, tuple(agents)) for source, agents in members.values()
        ]

    @property
    def needs_messages(self) -> bool:  # type: ignore[override]  # property over an attribute
        """True when any member reads ``BeliefRequest.messages``."""
        return any(bool(getattr(s, "needs_messages", True)) for s, _ in self.members)

    def source_for(self, agent: str) -> BeliefSource:
        """The source answering ``agent``; `ScenarioError` when there is no route and no default."""
        source = self.routes.get(agent, self.default)
        if source is None:
            raise ScenarioError(
                f"no belief source for agent {agent!r}: routed agents are "
                f"{', '.join(self.routes)} and there is no default source; add a "
                f"[feedback.agents.{agent}] table or a default [feedback].source"
            )
        return source

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Send each member its requests in one call; the answers in order (`iter_beliefs`)."""
        return in_order(self.iter_beliefs(requests), len(requests), self.name)

    def iter_beliefs(self, requests: Sequence[BeliefRequest]) -> Iterator[tuple[int, BeliefResult]]:
        """Yield ``(index, result)`` member by member, as each answers (its ``iter_beliefs``).

        `ScenarioError`: an agent without a source; `RuntimeError`: a member's count is wrong.
        """
        groups: dict[int, tuple[BeliefSource, list[int]]] = {}  # by member, in order of use
        for i, request in enumerate(requests):
            source = self.source_for(request.cluster)
            groups.setdefault(id(source), (source, []))[1].append(i)
        for source, indices in groups.values():
            batch = [requests[i] for i in indices]
            if not getattr(source, "needs_messages", True):  # keyed as when alone in a panel
                batch = [dataclasses.replace(r, messages=()) if r.messages else r for r in batch]
            iterate = getattr(source, "iter_beliefs", None)
            if callable(iterate):
                for j, result in iterate(batch):
                    yield indices[j], result
            else:
                yield from zip(indices, ask(source, batch), strict=True)

    def identity(self) -> dict[str, Any]:
        """Describe every member: ``{"routes": {agent: identity}, "default": identity}``."""
        return {
            "source": self.name,
            "routes": {agent: dict(s.identity()) for agent, s in sorted(self.routes.items())},
            "default": dict(self.default.identity()) if self.default is not None else None,
        }

    def close(self) -> None:
        """Close every distinct member once (the first error is raised after all)."""
        first: BaseException | None = None
        for source, _ in self.members:
            try:
                source.close()
            except Exception as error:  # close the others anyway
                first = first or error
        if first is not None:
            raise first
