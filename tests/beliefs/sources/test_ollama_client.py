"""OllamaSource against a mocked HTTP layer (``httpx.MockTransport``).

These tests check what is sent and how faults are handled; they do not replace the
real-server tests in ``test_ollama_client_live.py`` (``@pytest.mark.ollama``).
"""

from __future__ import annotations

import json
import threading
import time

import httpx
import numpy as np
import pytest
from fake_ollama import GOOD, chat_reply

from amuled_ma.beliefs import BeliefRequest, ScriptedSource, make_source
from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.clusters import build_messages
from amuled_ma.errors import BackendUnavailable, ModelNotFound
from amuled_ma.servers.hosts import resolve_host

MILK = ("up", "down", "left", "right")


class FakeServer:
    """A minimal Ollama API: /api/version, /api/tags and /api/chat, with scripted replies."""

    def __init__(self, replies=None, models=("amuled-tiny:latest",), delay=0.0):
        self.replies = replies or (lambda body, n: GOOD)
        self.models = models
        self.delay = delay
        self.chats: list[dict] = []
        self.in_flight = 0
        self.max_in_flight = 0
        self.lock = threading.Lock()

    def __call__(self, request: httpx.Request) -> httpx.Response:
        if request.url.path == "/api/version":
            return httpx.Response(200, json={"version": "0.0.0-fake"})
        if request.url.path == "/api/tags":
            models = [{"model": m, "name": m, "digest": "sha256:abc"} for m in self.models]
            return httpx.Response(200, json={"models": models})
        assert request.url.path == "/api/chat"
        body = json.loads(request.content)
        with self.lock:
            self.chats.append(body)
            n = len(self.chats)
            self.in_flight += 1
            self.max_in_flight = max(self.max_in_flight, self.in_flight)
        try:
            time.sleep(self.delay)
            reply = self.replies(body, n)
        finally:
            with self.lock:
                self.in_flight -= 1
        if isinstance(reply, httpx.Response):
            return reply
        if isinstance(reply, Exception):
            raise reply
        return chat_reply(body, reply)


def source(server, **kwargs):
    kwargs.setdefault("backoff_s", 0.001)
    return OllamaSource(host="http://fake:11434", transport=httpx.MockTransport(server), **kwargs)


def req(cluster="care", state="STATE", obs=(1.0,)):
    messages = build_messages(cluster, "findmilk", state)
    return BeliefRequest("findmilk", cluster, obs, MILK, messages)


def test_request_body_format_and_options():
    server = FakeServer()
    ollama = source(server, seed=7, num_ctx=4096)
    (result,) = ollama.beliefs([req()])
    assert result.status == "ok" and np.allclose(result.belief, [0.7, 0.1, 0.1, 0.1])
    assert result.prompt_tokens == 11 and result.completion_tokens == 5
    assert result.extra["reasoning"] == "go"
    body = server.chats[0]
    assert body["model"] == "amuled-tiny" and body["stream"] is False
    assert [m["role"] for m in body["messages"]] == ["system", *["user", "assistant"] * 3, "user"]
    assert body["messages"][-1]["content"].startswith("STATE\n\nBehave as an agent")
    assert body["format"]["required"] == ["reasoning", "0", "1", "2", "3"]
    assert body["options"]["temperature"] == 0
    assert body["options"]["seed"] == 7 and body["options"]["num_ctx"] == 4096
    unstructured = source(FakeServer(), structured=False)
    unstructured.beliefs([req()])


def test_identity_has_model_digest_and_options():
    ident = source(FakeServer()).identity()
    assert ident["model"] == "amuled-tiny" and ident["digest"] == "sha256:abc"
    assert ident["options"]["temperature"] == 0.0 and ident["options"]["seed"] == 42
    assert ident["format"]["structured"] is True
    other = source(FakeServer(), seed=1).identity()
    assert other != ident


def test_identical_requests_are_sent_once():
    server = FakeServer()
    ollama = source(server)
    results = ollama.beliefs([req(), req(), req("virtue"), req()])
    assert len(server.chats) == 2
    assert ollama.stats.deduplicated == 2 and ollama.stats.sent == 2
    assert all(r.status == "ok" for r in results)
    assert results[0].belief is not results[1].belief  # independent copies


def test_bounded_concurrency_and_grouping_by_system_prompt():
    server = FakeServer(delay=0.05)
    ollama = source(server, concurrency=3)
    ollama.beliefs([req(c, state=f"S{i}") for i in range(4) for c in ("care", "virtue")])
    assert server.max_in_flight == 3
    server = FakeServer()
    ollama = source(server, concurrency=1)

    def with_system(system, state):
        messages = (("system", system), *req(state=state).messages[1:])
        return BeliefRequest("findmilk", "care", (1.0,), MILK, messages)

    ollama.beliefs([with_system(s, f"{s}{i}") for i in range(2) for s in ("B", "A")])
    systems = [c["messages"][0]["content"] for c in server.chats]
    assert systems == ["A", "A", "B", "B"]


def test_timeout_counted_uniform_or_fallback():
    server = FakeServer(replies=lambda body, n: httpx.ReadTimeout("slow"))
    ollama = source(server)
    (result,) = ollama.beliefs([req()])
    assert result.status == "timeout" and np.allclose(result.belief, 0.25)
    assert ollama.stats.timeouts == 1 and ollama.stats.fallbacks == 1
    assert len(server.chats) == 1  # timeouts are not retried by default
    ollama = source(
        FakeServer(replies=lambda b, n: httpx.ReadTimeout("slow")), retry_timeouts=True, retries=2
    )
    ollama.beliefs([req()])
    assert ollama.stats.timeouts == 3 and ollama.stats.retries == 2
    fallback = ScriptedSource({"*": [0, 0, 0, 1]})
    ollama = source(FakeServer(replies=lambda b, n: httpx.ReadTimeout("slow")), fallback=fallback)
    (result,) = ollama.beliefs([req()])
    assert result.source == "scripted" and result.extra["ollama_failure"] == "timeout"


def test_transient_errors_retried_with_backoff():
    def flaky(body, n):
        return httpx.Response(503, json={"error": "busy"}) if n <= 2 else GOOD

    server = FakeServer(replies=flaky)
    ollama = source(server, retries=2, backoff_s=0.01)
    start = time.perf_counter()
    (result,) = ollama.beliefs([req()])
    assert result.status == "ok"
    assert ollama.stats.retries == 2 and ollama.stats.attempts == 3
    assert time.perf_counter() - start >= 0.01 + 0.02  # 0.01 then 0.02 s of backoff
    server = FakeServer(replies=lambda b, n: httpx.Response(503, json={"error": "busy"}))
    ollama = source(server, retries=1)
    (result,) = ollama.beliefs([req()])
    assert result.status == "error" and ollama.stats.errors == 1 and len(server.chats) == 2
    server = FakeServer(replies=lambda b, n: httpx.Response(400, json={"error": "bad"}))
    ollama = source(server, retries=3)
    assert ollama.beliefs([req()])[0].status == "error" and len(server.chats) == 1


def test_abstained_parse_is_reasked_with_another_seed():
    server = FakeServer(replies=lambda body, n: "no idea" if n == 1 else GOOD)
    ollama = source(server, parse_retries=1)
    (result,) = ollama.beliefs([req()])
    assert result.status == "ok" and result.extra["attempts"] == 2
    assert [c["options"]["seed"] for c in server.chats] == [42, 43]
    server = FakeServer(replies=lambda body, n: "never any JSON")
    ollama = source(server, parse_retries=2)
    (result,) = ollama.beliefs([req()])
    assert result.status == "abstained" and np.allclose(result.belief, 0.25)
    assert len(server.chats) == 3 and ollama.stats.abstained == 1
    assert result.raw == "never any JSON"


def test_free_text_reply_is_parsed():
    server = FakeServer(replies=lambda b, n: 'Reasoning. {"Move Up": 1.0}')
    (result,) = source(server, structured=False).beliefs([req()])
    assert result.status == "repaired" and np.allclose(result.belief, [1, 0, 0, 0])
    assert "key_names" in result.extra["repairs"]


def test_unreachable_server_is_one_clear_error_within_5s():
    def refuse(request):
        raise httpx.ConnectError("connection refused")

    ollama = OllamaSource(host="http://fake:1234", transport=httpx.MockTransport(refuse))
    with pytest.raises(BackendUnavailable) as info:
        ollama.beliefs([req()])
    message = str(info.value)
    assert "http://fake:1234" in message and "amuled ollama up" in message
    assert "ollama serve" in message
    start = time.perf_counter()
    with pytest.raises(BackendUnavailable, match=r"127\.0\.0\.1:9"):
        OllamaSource(host="127.0.0.1:9").check()  # nothing listens on the discard port
    assert time.perf_counter() - start < 5.0


def test_server_gone_mid_run_raises():
    server = FakeServer(replies=lambda b, n: httpx.ConnectError("gone"))
    with pytest.raises(BackendUnavailable, match="fake:11434"):
        source(server, retries=1).beliefs([req()])


def test_missing_model_names_model_and_command():
    with pytest.raises(ModelNotFound) as info:
        source(FakeServer(models=("other:latest",)), model="llama3.1:8b").check()
    message = str(info.value)
    assert "'llama3.1:8b'" in message and "ollama pull llama3.1:8b" in message
    assert "other:latest" in message
    with pytest.raises(ModelNotFound, match="ollama create amuled-tiny"):
        source(FakeServer(models=())).identity()
    gone = FakeServer(
        replies=lambda b, n: httpx.Response(404, json={"error": "model 'x' not found"})
    )
    with pytest.raises(ModelNotFound):
        source(gone).beliefs([req()])


def test_request_without_messages_is_an_error_result():
    bare = BeliefRequest("findmilk", "care", (1.0,), MILK)
    (result,) = source(FakeServer()).beliefs([bare])
    assert result.status == "error" and np.allclose(result.belief, 0.25)


def test_host_resolution(monkeypatch):
    monkeypatch.delenv("OLLAMA_HOST", raising=False)
    assert resolve_host() == "http://127.0.0.1:11434"
    monkeypatch.setenv("OLLAMA_HOST", "10.0.0.2:8080")
    assert resolve_host() == "http://10.0.0.2:8080"
    assert resolve_host("myhost") == "http://myhost:11434"
    assert resolve_host("https://example.com/") == "https://example.com:443"
    assert OllamaSource().host == "http://10.0.0.2:8080"


def test_make_source_and_cached_store_second_run_sends_nothing(tmp_path):
    from amuled_ma.beliefs.store.cached import CachedSource
    from amuled_ma.beliefs.store.database import BeliefStore

    server = FakeServer()
    ollama = make_source("ollama", host="http://fake:11434", transport=httpx.MockTransport(server))
    batch = [req(c, state=f"S{i}") for i in range(3) for c in ("care", "virtue")]
    with BeliefStore(tmp_path / "beliefs.sqlite") as store:
        first = CachedSource(ollama, store).beliefs(batch)
        assert len(server.chats) == 6
        cached = CachedSource(ollama, store)
        second = cached.beliefs(batch)
        assert len(server.chats) == 6 and cached.stats.hit_rate == 1.0
    for a, b in zip(first, second, strict=True):
        assert np.allclose(a.belief, b.belief)
    ollama.close()
