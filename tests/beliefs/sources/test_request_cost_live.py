"""The preflight's measured cost per request against the real tiny Ollama server (``ollama``).

Five answered requests go into a belief store; :func:`request_cost` reads their median;
three more distinct requests, timed here, must take within a factor of 2 of it each.
"""

from __future__ import annotations

import statistics
import time

import pytest
from ollama_server_fixture import ollama_host, ollama_model  # noqa: F401

from amuled_ma.beliefs import BeliefRequest
from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.keys import request_key
from amuled_ma.deliberation.build import request_cost

pytestmark = pytest.mark.ollama

MILK = ("up", "down", "left", "right")


def _request(i: int) -> BeliefRequest:
    text = (
        f"A robot at x={i}, y={i + 1} looks for milk. Actions: 0 up, 1 down, 2 left, "
        "3 right. Answer with a probability per action."
    )
    return BeliefRequest("findmilk", "care", (float(i), float(i + 1)), MILK, (("user", text),))


def test_estimate_within_factor_two_of_measured(ollama_host, ollama_model, tmp_path):  # noqa: F811
    source = OllamaSource(
        ollama_model,
        host=ollama_host,
        num_ctx=4096,
        num_predict=40,
        reasoning=False,
        concurrency=1,
        timeout_s=300,
        parse_retries=0,
    )
    try:
        source.beliefs([_request(100)])  # warm the model: a load is not a request's cost
        identity = source.identity()
        path = tmp_path / "b.sqlite"
        with BeliefStore(path) as store:
            for i in range(5):
                (result,) = source.beliefs([_request(i)])
                assert result.status in ("ok", "repaired"), (result.status, result.raw)
                store.put_many(
                    [(request_key(identity, _request(i)), identity, _request(i), result)]
                )
        cost = request_cost(path, ollama_model)
        assert cost.basis == "measured here: median of 5 recorded requests"
        walls = []
        for i in range(10, 13):
            start = time.perf_counter()
            source.beliefs([_request(i)])
            walls.append(time.perf_counter() - start)
    finally:
        source.close()
    actual = statistics.median(walls)
    assert cost.seconds / 2 <= actual <= 2 * cost.seconds, (cost.seconds, walls)
