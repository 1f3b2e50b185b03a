"""The preflight's cost per live request: the store's recorded median or the docs' figure."""

from __future__ import annotations

import numpy as np

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.keys import request_key
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult
from amuled_ma.deliberation.build import request_cost

ACTIONS = ("up", "down", "left", "right")


def _ident(model: str) -> dict[str, object]:
    return {"source": "ollama", "model": model, "digest": "sha256:abc", "options": {}}


def _put(
    store: BeliefStore, model: str, latencies: list[float], status: str = "ok", at: int = 0
) -> None:
    items = []
    for i, lat in enumerate(latencies, start=at):
        r = BeliefRequest("findmilk", "care", (float(i), 1.0), ACTIONS, (("user", "s"),))
        res = BeliefResult(np.ones(4) / 4, status, "ollama", raw="{}", latency_s=lat)
        items.append((request_key(_ident(model), r), _ident(model), r, res))
    store.put_many(items)


def test_median_of_recorded_requests(tmp_path) -> None:
    """Answered requests of 2, 3, 9, 4, 40 s: median 4 s.

    Another model's rows, failed requests and 0 s rows (answered without a request) are
    not counted.
    """
    path = tmp_path / "b.sqlite"
    with BeliefStore(path) as store:
        _put(store, "tiny", [2.0, 3.0, 9.0, 4.0, 40.0])
        _put(store, "other", [100.0] * 6)
        _put(store, "tiny", [7.0, 7.1, 7.2], status="error", at=10)
        _put(store, "tiny", [0.0, 0.0, 0.0], at=20)
    cost = request_cost(path, "tiny")
    assert cost.seconds == 4.0
    assert cost.basis == "measured here: median of 5 recorded requests"


def test_too_few_recorded_requests_says_not_measured(tmp_path) -> None:
    """Four recorded requests are below the minimum of 5: the docs' 4.1 s, said so."""
    path = tmp_path / "b.sqlite"
    with BeliefStore(path) as store:
        _put(store, "tiny", [1.0, 1.0, 1.0, 1.0])
    cost = request_cost(path, "tiny")
    assert cost.seconds == 4.1
    assert "not measured here" in cost.basis
    assert request_cost(tmp_path / "absent.sqlite", "tiny").seconds == 4.1
