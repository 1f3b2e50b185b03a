"""One belief store for a sweep on Ray: the driver's SQLite file, served by an actor.

A job on another node must not open that file (SQLite locks are unsafe over a network file
system), yet a state asked once anywhere must be a hit everywhere.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.errors import AmuledError


@ray.remote(num_cpus=0)
class BeliefStoreActor:
    """The driver's belief store, for the jobs on other nodes (one actor per store file)."""

    def __init__(self, path: str) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.store = BeliefStore(path)
        self.calls = {"lookup": 0, "put_many": 0, "keys_looked_up": 0, "rows_written": 0}

    def lookup(self, keys: list[str]) -> dict[str, Any]:
        """`BeliefStore.lookup` of ``keys``."""
        self.calls["lookup"] += 1
        self.calls["keys_looked_up"] += len(keys)
        return self.store.lookup(keys)

    def put_many(self, items: list[tuple]) -> int:
        """`BeliefStore.put_many` of ``items``; return the rows written."""
        written = self.store.put_many(items)
        self.calls["put_many"] += 1
        self.calls["rows_written"] += written
        return written

    def figures(self) -> dict[str, int]:
        """Calls served so far."""
        return dict(self.calls)

    def close(self) -> None:
        """Close the SQLite file."""
        self.store.close()


class RemoteStore:
    """A job's stand-in for the driver's store; a lost actor is a one-line `AmuledError`."""

    def __init__(self, actor: Any) -> None:
        self.actor = actor

    def _call(self, method: Any, argument: list) -> Any:
        try:
            return ray.get(method.remote(argument))
        except ray.exceptions.RayError as error:  # ActorDiedError, ActorUnavailableError, ...
            text = str(error).strip().splitlines()[0] if str(error).strip() else ""
            raise AmuledError(
                f"the sweep's belief store on the driver's node cannot be reached "
                f"({type(error).__name__}: {text[:200]}); check the driver's node "
                "('ray status'), then continue with --resume"
            ) from None

    def lookup(self, keys: Iterable[str]) -> dict[str, Any]:
        """Answers of ``keys`` from the driver's store."""
        return self._call(self.actor.lookup, list(keys))

    def put_many(self, items: Iterable[tuple]) -> int:
        """Write answers into the driver's store; return the rows written."""
        return self._call(self.actor.put_many, list(items))

    def close(self) -> None:
        """Nothing to release here (the driver closes the actor's file)."""


def start_store_actors(paths: Iterable[Path]) -> dict[str, Any]:
    """Start one `BeliefStoreActor` per store file, on this (the driver's) node."""
    here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
    # mypy types a @ray.remote class as the class, not Ray's ActorClass with .options
    actor = BeliefStoreActor.options  # type: ignore[attr-defined]
    return {
        str(path): actor(scheduling_strategy=here).remote(str(path))
        for path in sorted(set(map(str, paths)))
    }
