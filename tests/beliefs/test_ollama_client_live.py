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
from amuled_ma.beliefs.ollama import OllamaSource
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


def requests(clusters=("care", "deontological")):
    return [
        BeliefRequest("findmilk", c, (2.0, 3.0), MILK, build_messages(c, "findmilk", STATE))
        for c in clusters
    ]


@pytest.fixture
def live(ollama_host, ollama_model):
    source = OllamaSource(
        ollama_model,
        host=ollama_host,
        num_predict=96,
        reasoning_max_chars=60,
        concurrency=2,
        timeout_s=300,
    )
    yield source
    source.close()


def test_check_and_identity(live):
    digest = live.check()
    assert digest
    assert live.identity()["digest"] == digest


def test_paper_prompts_give_valid_structured_beliefs(live):
    results = live.beliefs(requests())
    for result in results:
        assert result.belief.shape == (4,)
        assert np.isclose(result.belief.sum(), 1.0) and np.all(result.belief >= 0)
        assert result.status in ("ok", "repaired"), (result.status, result.raw)
        assert result.prompt_tokens and result.prompt_tokens > 1000  # the full paper prompt
    assert live.stats.sent == 2 and live.stats.timeouts == 0


def test_deterministic_at_temperature_zero(live, ollama_host, ollama_model):
    (first,) = live.beliefs(requests(("virtue",)))
    again = OllamaSource(ollama_model, host=ollama_host, num_predict=96, reasoning_max_chars=60)
    try:
        (second,) = again.beliefs(requests(("virtue",)))
    finally:
        again.close()
    assert first.raw == second.raw
    assert np.array_equal(first.belief, second.belief)


def test_missing_model_on_a_real_server(ollama_host):
    with pytest.raises(ModelNotFound, match="ollama pull no-such-model-xyz"):
        OllamaSource("no-such-model-xyz", host=ollama_host).check()
