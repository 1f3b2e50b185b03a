"""Where a process opens the belief store: the SQLite file, or a service standing in for it.

Jobs of a sweep on several machines must share one belief store, so that no job asks a
state another job already asked. A machine that does not see the driver's files (or sees
them over a network file system, where SQLite's locks are not safe) must not open the
SQLite file itself. :func:`open_store` is how the code opens a store: the file, unless
this process was told, with :func:`serve_store_from`, to reach the store at that path
through a service (for a sweep on Ray: an actor on the driver's machine,
:mod:`amuled_ma.experiments.ray_store`).

A service is any object with the two methods :class:`~amuled_ma.beliefs.cached.CachedSource`
uses, ``lookup(keys)`` and ``put_many(items)``, plus ``close()``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Protocol

from amuled_ma.beliefs.store import BeliefStore


class StoreService(Protocol):
    """What :class:`~amuled_ma.beliefs.cached.CachedSource` needs of a store."""

    def lookup(self, keys: Any) -> dict[str, Any]:
        """Answers (``ok``/``repaired`` rows) of ``keys`` as cache-hit results."""

    def put_many(self, items: Any) -> int:
        """Write answers; return the rows written."""

    def close(self) -> None:
        """Release the service's handle."""


#: store path (resolved) -> the service that stands in for it in this process
_SERVICES: dict[str, StoreService] = {}


def _key(path: str | os.PathLike[str]) -> str:
    return str(Path(path).resolve())


def serve_store_from(path: str | os.PathLike[str], service: StoreService | None) -> None:
    """Open the store at ``path`` through ``service`` in this process (None: the file again).

    Args:
        path: The store's path as the driver knows it.
        service: The stand-in, or None to forget it.

    """
    if service is None:
        _SERVICES.pop(_key(path), None)
    else:
        _SERVICES[_key(path)] = service


def open_store(path: str | os.PathLike[str]) -> BeliefStore | StoreService:
    """Open the belief store at ``path``: its service when one is set, else the file.

    Args:
        path: The store file (its folder is created for the file).

    Returns:
        The :class:`~amuled_ma.beliefs.store.BeliefStore`, or the service standing in.

    """
    service = _SERVICES.get(_key(path))
    if service is not None:
        return service
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return BeliefStore(path)
