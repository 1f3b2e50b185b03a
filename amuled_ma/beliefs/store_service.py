"""What stands in for the belief store, and how a run's store file is opened.

Jobs of a sweep on several machines must share one belief store, so that no job asks a
state another job already asked. A machine that does not see the driver's files (or sees
them over a network file system, where SQLite's locks are not safe) must not open the
SQLite file itself: its job is given a service instead (for a sweep on Ray: a stand-in for
an actor on the driver's machine, `ray_store`), passed in as the
``store`` of `train_variant`. A service is any object with
the methods `CachedSource` uses (`StoreService`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from amuled_ma.beliefs.store import BeliefStore
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


def open_store(path: str | os.PathLike[str]) -> BeliefStore:
    """Open the belief store file at ``path``, creating its folder.

    Args:
        path: The store file.

    Returns:
        The `BeliefStore`.

    """
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return BeliefStore(path)
