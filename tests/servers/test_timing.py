"""Per-request timings of the Ollama source (``amuled_ma.servers.timing``), without a server.

Ollama's metrics come from a mocked ``/api/chat`` (``httpx.MockTransport``); the real tiny
model's figures are checked by ``tests/integration/test_live_demo.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest

from amuled_ma.beliefs import BeliefRequest
from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.servers.timing import (
    CacheReuse,
    RequestTiming,
    cache_reuse,
    record_timings,
    timing_breakdown,
)

MILK = ("up", "down", "left", "right")
METRICS = {  # nanoseconds, as Ollama sends them
    "total_duration": 3_000_000_000,
    "load_duration": 100_000_000,
    "prompt_eval_count": 3646,
    "prompt_eval_duration": 500_000_000,
    "eval_count": 40,
    "eval_duration": 2_000_000_000,
}


def chat_server(replies: list[str]):
    """A mocked Ollama answering ``/api/chat`` with ``replies`` in turn, metrics included."""
    calls = []

    def handle(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/api/tags":
            return httpx.Response(200, json={"models": [{"model": "amuled-tiny:latest"}]})
        if request.url.path == "/api/version":
            return httpx.Response(200, json={"version": "0.0.0-fake"})
        calls.append(json.loads(request.content))
        content = replies[min(len(calls), len(replies)) - 1]
        return httpx.Response(
            200,
            json={"message": {"role": "assistant", "content": content}, "done": True, **METRICS},
        )

    return handle, calls


def request(cluster: str = "care", obs: tuple[float, ...] = (1.0,)) -> BeliefRequest:
    return BeliefRequest("findmilk", cluster, obs, MILK, (("user", f"state {obs}"),))


def test_from_reply_reads_ollamas_nanoseconds_and_sums_calls() -> None:
    class Reply:
        pass

    reply = Reply()
    for key, value in METRICS.items():
        setattr(reply, key, value)
    one = RequestTiming.from_reply(reply, wall_s=3.25)
    assert one == RequestTiming(1, 0.1, 3646, 0.5, 40, 2.0, 3.0, 3.25)
    two = one + one
    assert two.calls == 2 and two.prompt_tokens == 7292 and two.decode_s == pytest.approx(4.0)
    assert RequestTiming.from_dict(two.as_dict()) == two
    assert RequestTiming.from_reply(Reply(), 0.0) == RequestTiming(calls=1)  # no metrics: 0


def test_each_answer_keeps_its_timing_and_the_store_round_trips_it(tmp_path: Path) -> None:
    good = json.dumps({"0": 0.7, "1": 0.1, "2": 0.1, "3": 0.1})
    handle, calls = chat_server(["not json at all", good, good])
    source = OllamaSource(host="http://fake:11434", transport=httpx.MockTransport(handle))
    with record_timings() as log:
        first, second = source.beliefs([request("care"), request("virtue", (2.0,))])
    assert len(calls) == 3  # the abstained first reply was re-asked once
    assert len(log.timings) == 2 and sum(t.calls for t in log.timings) == 3
    assert log.span_s > 0
    timings = {r.extra["timing"]["calls"]: RequestTiming.from_dict(r.extra["timing"])
               for r in (first, second)}  # fmt: skip
    assert timings[2].prompt_tokens == 2 * 3646 and timings[2].prefill_s == pytest.approx(1.0)
    assert timings[1].decode_tokens == 40 and timings[1].total_s == pytest.approx(3.0)
    with BeliefStore(tmp_path / "beliefs.sqlite") as store:
        store.put_many([("k1", {"source": "ollama"}, request("care"), first)])
        assert store.get("k1").extra["timing"] == first.extra["timing"]
    with record_timings() as outside:
        pass
    assert outside.timings == [] and outside.span_s == 0.0  # nothing asked in the block


def test_cache_reuse_reads_the_debug_log_from_an_offset(tmp_path: Path) -> None:
    line = (
        'time=2026-11-30T12:33:55.631Z level=DEBUG source=cache.go:104 msg="loading cache '
        'slot" id=0 cache={cache} prompt={prompt} used={used} remaining={rest}\n'
    )
    log = tmp_path / "server.log"
    log.write_text("level=INFO msg=other\n" + line.format(cache=0, prompt=3646, used=0, rest=3646))
    offset = log.stat().st_size
    with log.open("a") as out:
        out.write(line.format(cache=3700, prompt=3646, used=3600, rest=46))
        out.write(line.format(cache=3700, prompt=3646, used=3348, rest=298))
    assert cache_reuse(log) == CacheReuse(3, 3 * 3646, 6948)
    later = cache_reuse(log, offset)
    assert later == CacheReuse(2, 7292, 6948) and later.evaluated_tokens == 344
    assert cache_reuse(tmp_path / "missing.log") is None
    log.write_text("level=INFO only\n")
    assert cache_reuse(log) is None  # no debug lines: not known


def test_breakdown_names_every_figure() -> None:
    one = RequestTiming(1, 0.1, 3646, 0.5, 40, 2.0, 3.0, 3.25)
    lines = timing_breakdown([one, one], wall_s=4.0, reuse=CacheReuse(2, 7292, 3646))
    text = "\n".join(lines)
    assert lines[0].startswith("requests 2 (2 chat calls")
    assert "mean 3646, median 3646; prefill (prompt eval) mean 0.50 s" in text
    assert "mean 40, median 40; decode (JSON schema) mean 2.00 s" in text
    assert "20.0 tokens/s" in text
    assert "7,292 prompt tokens sent in 2 calls, 3,646 reused (50%), 3,646 evaluated" in text
    assert "6.5 s at the client, 6.0 s at the server = prefill 1.0 + decode 4.0" in text
    assert "model load 0.2" in text and "wall = 1.62 requests in flight" in text
    assert "not known" in timing_breakdown([one])[3]
    assert timing_breakdown([]) == ["no live requests (every belief came from the belief store)"]
