"""One belief store for a sweep on Ray: the driver's SQLite file, served by an actor.

A job on another machine must not ask a state another job already asked, and must not
open the driver's SQLite file (it may not see it; over a network file system SQLite's
locks are not safe). :class:`BeliefStoreActor` opens the store on the driver's node (Ray
pins it there) and answers ``lookup`` / ``put_many``; :class:`RemoteStore` is the
stand-in a job on another node opens instead of the file
(:func:`amuled_ma.beliefs.store_service.serve_store_from`). Jobs on the driver's node
open the file itself (SQLite WAL is safe across the processes of one machine).

Why this design (docs/scale.md): no server to install (PostgreSQL would be one more
service to run and secure), the same rows and keys as every other run (the actor holds
the very :class:`~amuled_ma.beliefs.store.BeliefStore`), and a state asked once anywhere
in the sweep is a store hit everywhere after, as on one machine. Per-node stores merged
at the end of each stage would let the fine-tunes of one stage, which visit mostly the
same states, each ask them again.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from amuled_ma.beliefs.store import BeliefStore


@ray.remote(num_cpus=0)
class BeliefStoreActor:
    """The driver's belief store, for the jobs on other nodes (one actor per store file)."""

    def __init__(self, path: str) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.store = BeliefStore(path)
        self.calls = {"lookup": 0, "put_many": 0, "keys_looked_up": 0, "rows_written": 0}

    def lookup(self, keys: list[str]) -> dict[str, Any]:
        """:meth:`BeliefStore.lookup` of ``keys``."""
        self.calls["lookup"] += 1
        self.calls["keys_looked_up"] += len(keys)
        return self.store.lookup(keys)

    def put_many(self, items: list[tuple]) -> int:
        """:meth:`BeliefStore.put_many` of ``items``; return the rows written."""
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
    """A job's stand-in for the driver's store: each call goes to the store's actor."""

    def __init__(self, actor: Any) -> None:
        self.actor = actor

    def lookup(self, keys: Iterable[str]) -> dict[str, Any]:
        """Answers of ``keys`` from the driver's store."""
        return ray.get(self.actor.lookup.remote(list(keys)))

    def put_many(self, items: Iterable[tuple]) -> int:
        """Write answers into the driver's store; return the rows written."""
        return ray.get(self.actor.put_many.remote(list(items)))

    def close(self) -> None:
        """Nothing to release here (the driver closes the actor's file)."""


def start_store_actors(paths: Iterable[Path]) -> dict[str, Any]:
    """Start one :class:`BeliefStoreActor` per store file, on this (the driver's) node."""
    here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
    return {
        str(path): BeliefStoreActor.options(scheduling_strategy=here).remote(str(path))
        for path in sorted(set(map(str, paths)))
    }
