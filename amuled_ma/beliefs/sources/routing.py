"""`RoutedSource`: one batch split across the panel members' sources, one call per member.

See ``docs/beliefs.md``, "Per-agent sources".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, every_answer
from amuled_ma.errors import ScenarioError


# ----------------------------------------------------------------------------- routing
class RoutedSource(BeliefSource):
    """Answer each request with the source of its agent (``request.cluster``).

    Args:
        routes: ``{agent name: source}``; the same source object may serve several agents
            (it then gets their requests in one call).
        default: The source of every agent without a route (``None``: such a request is
            an error).

    Raises:
        ValueError: No route and no default.

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
        """Return the source answering ``agent``.

        Raises:
            ScenarioError: No route and no default source.

        """
        source = self.routes.get(agent, self.default)
        if source is None:
            raise ScenarioError(
                f"no belief source for agent {agent!r}: routed agents are "
                f"{', '.join(self.routes)} and there is no default source; add a "
                f"[feedback.agents.{agent}] table or a default [feedback].source"
            )
        return source

    def _split(self, requests: Sequence[BeliefRequest]) -> list[tuple[BeliefSource, list[int]]]:
        """Group request indices by member source, members in order of first request."""
        groups: dict[int, tuple[BeliefSource, list[int]]] = {}
        for i, request in enumerate(requests):
            source = self.source_for(request.cluster)
            groups.setdefault(id(source), (source, []))[1].append(i)
        return list(groups.values())

    @staticmethod
    def _sub_batch(
        source: BeliefSource, requests: Sequence[BeliefRequest], indices: list[int]
    ) -> list[BeliefRequest]:
        """The member's requests; without messages for a member that reads none.

        Dropping the chat for replay, rules and policy members keeps their store keys
        the same as when they serve a whole panel alone (the panel sends no chat then).
        """
        if getattr(source, "needs_messages", True):
            return [requests[i] for i in indices]
        return [
            dataclasses.replace(requests[i], messages=()) if requests[i].messages else requests[i]
            for i in indices
        ]

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Send each member its requests in one call; return the answers in order.

        Raises `ScenarioError` for a request whose agent has no source, `RuntimeError` when a
        member answers a different number of results.
        """
        out: list[BeliefResult | None] = [None] * len(requests)
        for source, indices in self._split(requests):
            results = source.beliefs(self._sub_batch(source, requests, indices))
            if len(results) != len(indices):
                raise RuntimeError(
                    f"belief source {getattr(source, 'name', '?')!r} answered {len(results)} "
                    f"results for {len(indices)} requests"
                )
            for i, result in zip(indices, results, strict=True):
                out[i] = result
        return every_answer(out, self.name)

    def iter_beliefs(self, requests: Sequence[BeliefRequest]) -> Iterator[tuple[int, BeliefResult]]:
        """Yield ``(index, result)`` member by member, as each member answers.

        A member with ``iter_beliefs`` yields as its answers arrive; any other member's
        answers come after its one call.
        """
        for source, indices in self._split(requests):
            batch = self._sub_batch(source, requests, indices)
            iterate = getattr(source, "iter_beliefs", None)
            if callable(iterate):
                for j, result in iterate(batch):
                    yield indices[j], result
            else:
                for i, result in zip(indices, source.beliefs(batch), strict=True):
                    yield i, result

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
