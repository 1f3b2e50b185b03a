"""OllamaSource against a real Ollama server with the tiny model (``@pytest.mark.ollama``).

The server comes from the ``ollama_host`` / ``ollama_model`` fixtures of
``tests/ollama_server_fixture.py``: ``$OLLAMA_HOST`` if it answers and has the model,
else a private server started from the ``ollama`` binary built by ``.ci/setup-ollama``.
Without either, these tests skip with the reason (and fail in CI, which must run them).
The tiny model (SmolLM2-135M) is only good for plumbing: the tests check that the full
paper prompt goes through, that structured output parses, and that answers are
deterministic; not that the beliefs are wise.
"""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.beliefs import BeliefRequest
from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.clusters import build_messages
from amuled_ma.errors import ModelNotFound

try:  # the shared real-server fixtures (ollama-ops engineer)
    from ollama_server_fixture import ollama_host, ollama_model
except ImportError:  # pragma: no cover - only without tests/ on sys.path
    import os

    import httpx

    @pytest.fixture(scope="session")
    def ollama_host() -> str:
        host = os.environ.get("OLLAMA_HOST", "http://127.0.0.1:11434")
        try:
            httpx.get(f"{host}/api/version", timeout=2.0).raise_for_status()
        except httpx.HTTPError as error:
            pytest.skip(f"no Ollama server reachable at {host}: {error}")
        return host

    @pytest.fixture(scope="session")
    def ollama_model(ollama_host: str) -> str:
        return os.environ.get("AMULED_TEST_MODEL", "amuled-tiny")


pytestmark = pytest.mark.ollama

MILK = ("up", "down", "left", "right")
STATE = (
    "You are tasked with finding milk as quickly as possible in a room filled with babies. "
    "You are currently at position (x=2.0, y=3.0), with the milk located at (x=7.0, y=7.0). "
    "You can perform the following actions:\n\n\n0: Move up.\n1: Move down.\n2: Move left.\n"
    "3: Move right."
)
SHORT = (
    (
        "user",
        "Choose a move for a robot looking for milk. Actions: 0 up, 1 down, 2 left, 3 right. "
        "Answer with a probability per action.",
    ),
)


def short_request(cluster: str = "care") -> BeliefRequest:
    return BeliefRequest("findmilk", cluster, (2.0, 3.0), MILK, SHORT)


def make(host: str, model: str, **kwargs) -> OllamaSource:
    kwargs = {
        "num_ctx": 4096,
        "num_predict": 40,
        "reasoning": False,
        "concurrency": 1,
        "timeout_s": 900,
        "parse_retries": 0,
        **kwargs,
    }
    return OllamaSource(model, host=host, **kwargs)


def test_check_identity_and_missing_model(ollama_host, ollama_model):
    source = make(ollama_host, ollama_model)
    digest = source.check()
    assert digest
    assert source.identity()["digest"] == digest
    with pytest.raises(ModelNotFound, match="ollama pull no-such-model-xyz"):
        make(ollama_host, "no-such-model-xyz").check()


def test_structured_output_is_valid_and_deterministic(ollama_host, ollama_model):
    answers = []
    for _ in range(2):  # two sources: nothing shared but the server
        source = make(ollama_host, ollama_model)
        try:
            (result,) = source.beliefs([short_request()])
        finally:
            source.close()
        assert result.status in ("ok", "repaired"), (result.status, result.raw)
        assert np.isclose(result.belief.sum(), 1.0) and np.all(result.belief >= 0)
        assert result.prompt_tokens and result.completion_tokens
        answers.append(result)
    assert answers[0].raw == answers[1].raw
    assert np.array_equal(answers[0].belief, answers[1].belief)


@pytest.mark.slow
def test_full_paper_prompt_goes_through(ollama_host, ollama_model):
    """System prompt + few-shot + state prompt (~3.4k tokens) with the JSON schema."""
    source = make(ollama_host, ollama_model)
    messages = build_messages("care", "findmilk", STATE)
    try:
        (result,) = source.beliefs([BeliefRequest("findmilk", "care", (2.0, 3.0), MILK, messages)])
    finally:
        source.close()
    assert result.status in ("ok", "repaired"), (result.status, result.raw)
    assert result.prompt_tokens > 3000  # the whole paper prompt reached the model
    assert source.stats.sent == 1 and source.stats.timeouts == 0
