"""Structured beliefs from a real Ollama server (the tiny SmolLM2 model).

The tiny model's moral judgement is meaningless; these tests check the plumbing for real:
the paper's prompts go through the official client with a JSON-schema ``format``, come
back as valid belief vectors for every cluster of both tasks, are deterministic at
temperature 0, and land in the belief store so that a second run sends nothing.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import ollama
import pytest
from _live_helpers import OPTIONS, TASKS, chat

from amuled_ma.beliefs import BeliefRequest, belief_schema, parse_belief
from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.clusters import build_messages, default_registry


def _requests(task: str) -> list[BeliefRequest]:
    spec = TASKS[task]
    return [
        BeliefRequest(
            task=task,
            cluster=cluster.name,
            obs=(0.0,),
            action_names=spec["actions"],
            # The paper's system prompt (five clusters) and each agent's instruction; the
            # few-shot block (~2,000 more tokens, identical for every agent) is left out:
            # its prefill costs minutes on a busy 2-core CPU and tests no extra plumbing.
            messages=build_messages(cluster, task, spec["state"], fewshot=False),
        )
        for cluster in default_registry().all()
    ]


def _source(host: str, model: str) -> OllamaSource:
    return OllamaSource(
        model,
        host=host,
        reasoning=False,
        num_ctx=OPTIONS["num_ctx"],
        num_predict=OPTIONS["num_predict"],
        concurrency=1,  # one cold prefill of the shared prefix, then warm (one slot)
        timeout_s=300,
    )


def test_raw_client_structured_output_is_schema_valid_and_deterministic(
    ollama_host: str, ollama_model: str
) -> None:
    """The official client with ``format=<schema>``, temperature 0 and a seed."""
    actions = TASKS["driving"]["actions"]
    schema = belief_schema(actions, reasoning=False)
    messages = (
        ("system", "You answer with a probability for each action as JSON."),
        ("user", TASKS["driving"]["state"]),
    )
    client = ollama.Client(host=ollama_host, timeout=120)
    replies = [chat(client, ollama_model, messages, schema).message.content for _ in range(2)]
    assert replies[0] == replies[1], "temperature 0 + fixed seed must repeat the answer"
    data = json.loads(replies[0] or "")
    assert set(data) == set(schema["properties"])
    assert all(isinstance(v, int | float) for v in data.values())
    parsed = parse_belief(replies[0], actions, structured=True)
    assert parsed.belief.shape == (len(actions),)
    # Ollama does not enforce minimum/maximum: our parser validates and normalises.
    if parsed.status != "abstained":
        assert np.isclose(parsed.belief.sum(), 1.0) and (parsed.belief >= 0).all()


@pytest.mark.slow
def test_every_cluster_of_both_tasks_then_the_store_answers_everything(
    ollama_host: str, ollama_model: str, tmp_path: Path
) -> None:
    """All six agents x both tasks, through OllamaSource + the persistent store, twice."""
    requests = _requests("findmilk") + _requests("driving")
    clusters = {r.cluster for r in requests}
    assert {"care", "consequentialist", "deontological", "virtue", "social_justice"} <= clusters
    assert len(requests) == 2 * len(clusters)

    store_path = tmp_path / "beliefs.sqlite"
    source = _source(ollama_host, ollama_model)
    with BeliefStore(store_path) as store:
        first = CachedSource(source, store).beliefs(requests)
    source.close()
    for request, result in zip(requests, first, strict=True):
        assert result.status in {"ok", "repaired", "abstained"}, (request.cluster, result.extra)
        assert result.belief.shape == (request.num_actions,)
        assert np.isclose(result.belief.sum(), 1.0) and (result.belief >= 0).all()
        assert result.raw, "the real reply is kept"
        assert not result.cached
    answered = sum(r.status in {"ok", "repaired"} for r in first)
    assert answered >= 0.75 * len(requests), [(r.status, r.raw) for r in first]
    assert source.stats.sent == len(requests) and source.stats.timeouts == 0

    # Second run, a fresh source and store handle (as a new process): only cacheable
    # answers are served, and nothing answered is asked again.
    again = _source(ollama_host, ollama_model)
    with BeliefStore(store_path) as store:
        cached = CachedSource(again, store)
        second = cached.beliefs(requests)
    again.close()
    assert cached.stats.hits == answered
    assert again.stats.sent == len(requests) - answered
    if answered == len(requests):
        assert cached.stats.hit_rate == 1.0 and again.stats.attempts == 0
    for a, b in zip(first, second, strict=True):
        if a.status in {"ok", "repaired"}:
            assert b.cached and np.array_equal(a.belief, b.belief)
