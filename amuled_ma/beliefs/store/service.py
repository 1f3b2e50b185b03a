"""What may stand in for the belief store (`StoreService`).

A node that cannot open the SQLite file safely (another machine, a network file system) is
handed a service instead (for Ray: `amuled_ma.experiments.ray_store`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult

#: One answer to write: ``(key, source identity, request, result)``.
StoreItem = tuple[str, Mapping[str, Any] | str, BeliefRequest, BeliefResult]


class StoreService(Protocol):
    """What `CachedSource` needs of a store."""

    def lookup(self, keys: list[str]) -> dict[str, BeliefResult]:
        """Answers (``ok``/``repaired`` rows) of ``keys`` as cache-hit results."""

    def put_many(self, items: Sequence[StoreItem]) -> int:
        """Write answers; return the rows written."""

    def close(self) -> None:
        """Release the service's handle."""
