"""OllamaSource over a pool of servers (``hosts=[...]``), against mocked HTTP servers.

Each fake server is an ``httpx.MockTransport`` handler; one transport routes by the host of
each request's URL. The real two-server test with a ``kill -9`` is
``tests/integration/test_live_host_pool.py``. Also: the ``hosts`` scenario keys, the figures in
the feedback summary, ``results.json`` merging and the report's table.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time

import httpx
import numpy as np
import pytest
from fake_ollama import GOOD, chat_reply

from amuled_ma.beliefs import BeliefRequest
from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.errors import BackendUnavailable, ModelNotFound, ScenarioError
from amuled_ma.evaluate.results import Results

MILK = ("up", "down", "left", "right")
A, B = "http://gpu1:11434", "http://gpu2:11434"


class Fake:
    """One fake Ollama server; ``dead`` makes every call fail with a connection error."""

    def __init__(self, digest: str = "sha256:abc", delay: float = 0.0) -> None:
        self.digest = digest
        self.delay = delay
        self.dead = False
        self.hang = False
        self.chats = 0
        self.lock = threading.Lock()

    def __call__(self, request: httpx.Request) -> httpx.Response:
        if self.dead:
            raise httpx.ConnectError("connection refused", request=request)
        if request.url.path == "/api/version":
            return httpx.Response(200, json={"version": "0.0.0-fake"})
        if request.url.path == "/api/tags":
            model = {"model": "amuled-tiny:latest", "name": "amuled-tiny:latest"}
            return httpx.Response(200, json={"models": [{**model, "digest": self.digest}]})
        if self.hang:
            raise httpx.ReadTimeout("timed out", request=request)
        with self.lock:
            self.chats += 1
        time.sleep(self.delay)
        body = json.loads(request.content)
        return chat_reply(body, GOOD)


def router(servers: dict[str, Fake]) -> httpx.MockTransport:
    def handle(request: httpx.Request) -> httpx.Response:
        return servers[f"http://{request.url.host}:{request.url.port}"](request)

    return httpx.MockTransport(handle)


def pool_source(servers: dict[str, Fake], **kwargs: object) -> OllamaSource:
    kwargs.setdefault("backoff_s", 0.001)
    return OllamaSource(hosts=list(servers), transport=router(servers), **kwargs)  # type: ignore[arg-type]


def req(i: int, cluster: str = "care") -> BeliefRequest:
    messages = (("system", "SYSTEM"), ("user", f"state {i}"))
    return BeliefRequest("findmilk", cluster, (float(i),), MILK, messages)


def test_requests_are_spread_and_the_figures_add_up() -> None:
    servers = {A: Fake(delay=0.02), B: Fake(delay=0.02)}
    source = pool_source(servers, concurrency=2)
    results = source.beliefs([req(i) for i in range(10)])
    assert all(r.status == "ok" for r in results)
    figures = source.server_stats()
    assert list(figures) == [A, B]
    assert figures[A]["sent"] >= 3 and figures[B]["sent"] >= 3  # least busy: both used
    assert figures[A]["sent"] + figures[B]["sent"] == source.stats.attempts == 10
    assert servers[A].chats == figures[A]["answered"] and servers[B].chats == figures[B]["answered"]
    assert {r.extra["host"] for r in results} == {A, B}
    assert figures[A]["mean_latency_s"] >= 0.02 and figures[A]["failed"] == 0


def test_a_host_that_dies_mid_batch_is_left_out_and_its_requests_retried(tmp_path) -> None:
    servers = {A: Fake(delay=0.02), B: Fake(delay=0.02)}
    source = pool_source(servers, concurrency=2, down_for_s=60)
    written: list[str] = []
    with BeliefStore(tmp_path / "beliefs.sqlite") as store:
        put_many = store.put_many

        def counting(rows):  # every row written, to show none is written twice
            rows = list(rows)
            written.extend(key for key, *_ in rows)
            return put_many(rows)

        store.put_many = counting  # type: ignore[method-assign]
        cached = CachedSource(source, store)
        requests = [req(i) for i in range(12)]
        done = threading.Event()

        def kill_after_first_answer() -> None:
            while servers[A].chats < 1 and not done.is_set():
                time.sleep(0.001)
            servers[A].dead = True

        killer = threading.Thread(target=kill_after_first_answer)
        killer.start()
        results = cached.beliefs(requests)
        done.set()
        killer.join()
    assert [r.status for r in results] == ["ok"] * 12
    keys = cached.keys(requests)
    assert sorted(written) == sorted(keys)  # each answer written once
    rows = sqlite3.connect(tmp_path / "beliefs.sqlite").execute("SELECT COUNT(*) FROM beliefs")
    assert rows.fetchone()[0] == 12
    a, b = source.server_stats()[A], source.server_stats()[B]
    assert a["failures"] == {"connection": 1} and a["retried_from"] == 1 and a["went_down"] == 1
    assert a["live"] is False and b["failed"] == 0
    assert a["answered"] + b["answered"] == 12 and source.stats.failovers == 1
    assert a["sent"] + b["sent"] == source.stats.attempts == 13  # 12 + the one retried
    assert sum(r.extra["host"] == B for r in results) == b["answered"]


def test_a_timeout_takes_the_host_out_and_the_request_goes_elsewhere() -> None:
    servers = {A: Fake(), B: Fake()}
    servers[A].hang = True
    source = pool_source(servers, concurrency=1, down_for_s=60)
    results = source.beliefs([req(i) for i in range(3)])
    assert [r.status for r in results] == ["ok"] * 3
    a = source.server_stats()[A]
    assert a["failures"] == {"timeout": 1} and a["sent"] == 1 and a["retried_from"] == 1
    assert source.stats.timeouts == 1 and source.stats.failovers == 1


def test_every_attempt_timing_out_is_a_timeout_result_not_an_endless_loop() -> None:
    servers = {A: Fake(), B: Fake()}
    servers[A].hang = servers[B].hang = True
    source = pool_source(servers, down_for_s=0.01)
    (result,) = source.beliefs([req(0)])
    assert result.status == "timeout"
    assert source.stats.attempts == 3  # len(hosts) + 1


def test_a_host_that_comes_back_is_used_again() -> None:
    servers = {A: Fake(), B: Fake()}
    source = pool_source(servers, concurrency=1, down_for_s=0.05)
    source.check()
    servers[A].dead = True
    assert all(r.status == "ok" for r in source.beliefs([req(i) for i in range(2)]))
    assert source.server_stats()[A]["live"] is False
    servers[A].dead = False
    time.sleep(0.06)
    source.beliefs([req(i) for i in range(2, 5)])
    a = source.server_stats()[A]
    assert a["came_back"] == 1 and a["live"] is True and a["answered"] >= 1


def test_every_host_dead_is_one_error_naming_all_in_bounded_time() -> None:
    servers = {A: Fake(), B: Fake()}
    source = pool_source(servers, down_for_s=0.05)
    source.check()
    servers[A].dead = servers[B].dead = True
    start = time.monotonic()
    with pytest.raises(BackendUnavailable) as info:
        source.beliefs([req(i) for i in range(4)])
    assert time.monotonic() - start < 5
    message = str(info.value)
    assert A in message and B in message and "remove the dead ones" in message
    assert sum(row["sent"] for row in source.server_stats().values()) == source.stats.attempts


def test_start_check_every_host_the_same_digest() -> None:
    mismatch = pool_source({A: Fake(), B: Fake(digest="sha256:other")})
    with pytest.raises(ModelNotFound) as info:
        mismatch.check()
    message = str(info.value)
    assert "'sha256:abc'" in message and "'sha256:other'" in message
    assert A in message and B in message and "remove http://gpu2:11434" in message
    dead = {A: Fake(), B: Fake()}
    dead[B].dead = True
    with pytest.raises(BackendUnavailable) as info:
        pool_source(dead).check()
    message = str(info.value)
    assert "1 of the 2 Ollama servers" in message and B in message
    assert f"remove {B} from the pool" in message


def test_identity_and_store_keys_do_not_depend_on_the_hosts() -> None:
    pool = pool_source({A: Fake(), B: Fake()})
    single = OllamaSource(host=A, transport=router({A: Fake()}))
    assert pool.identity() == single.identity()
    assert "gpu" not in json.dumps(pool.identity())


def test_bad_host_lists_are_refused() -> None:
    with pytest.raises(ScenarioError, match="both given"):
        OllamaSource(host=A, hosts=[B])
    with pytest.raises(ScenarioError, match="at least one server URL"):
        OllamaSource(hosts=[])
    with pytest.raises(ScenarioError, match=r"hosts\[1\] 'gpu1' is http://gpu1:11434"):
        OllamaSource(hosts=[A, "gpu1"])
    with pytest.raises(ScenarioError, match="expects a list"):
        OllamaSource(hosts="http://gpu1")  # type: ignore[arg-type]


def test_one_host_keeps_its_retries_with_backoff() -> None:
    server = Fake()
    server.dead = True
    source = OllamaSource(host=A, transport=router({A: server}), retries=2, backoff_s=0.001)
    source._digest = ""  # the server died after the start check
    with pytest.raises(BackendUnavailable, match="no Ollama server answers at http://gpu1"):
        source.beliefs([req(0)])
    assert source.stats.attempts == 3 and source.stats.retries == 2
    assert source.server_stats()[A]["failures"] == {"connection": 3}
    assert source.server_stats()[A]["live"] is True  # a pool of one never goes down


# -- scenario keys ---------------------------------------------------------------------
def test_scenario_hosts_key_and_its_errors(tmp_path) -> None:
    from amuled_ma.deliberation.plan import default_source
    from amuled_ma.scenario import load_scenario
    from amuled_ma.scenario.overrides import parse_set

    path = tmp_path / "pool.toml"
    path.write_text(
        '[feedback]\nsource = "ollama"\nmodel = "amuled-tiny"\n'
        'hosts = ["gpu1", "http://gpu2:11434"]\n'
    )
    scenario = load_scenario(path)
    assert scenario.feedback.hosts == ["gpu1", "http://gpu2:11434"]
    spec = default_source(scenario.feedback, scenario.resolve, scenario.name)
    assert spec.options["hosts"] == ["gpu1", "http://gpu2:11434"]
    assert spec.options["host"] is None
    path.write_text('[feedback]\nhost = "gpu0"\nhosts = ["gpu1"]\n')
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert "keys [feedback].host ('gpu0') and [feedback].hosts" in str(info.value)
    assert str(path) in str(info.value)
    path.write_text('[feedback]\nhosts = ["gpu1", "ftp://gpu2"]\n')
    with pytest.raises(ScenarioError, match=r"key \[feedback\]\.hosts\[1\] 'ftp://gpu2'"):
        load_scenario(path)
    section, key, value = parse_set('feedback.hosts=["http://a:1", "http://b:2"]')
    changed = load_scenario("findmilk").replace(section, **{key: value})
    assert changed.feedback.hosts == ["http://a:1", "http://b:2"]
    with pytest.raises(ScenarioError, match=r"\[feedback.ollama\] unknown key\(s\) hosts"):
        load_scenario("findmilk").replace("feedback", ollama={"hosts": ["http://a:1"]})


def test_agent_tables_take_hosts(tmp_path) -> None:
    from amuled_ma.deliberation.plan import agent_source
    from amuled_ma.scenario import OllamaSpec, load_scenario

    base = load_scenario("findmilk").replace("feedback", hosts=["http://a:1", "http://b:2"])
    care = {"source": "ollama", "model": "m", "hosts": ["http://c:3", "http://d:4"]}
    scenario = base.replace("feedback", agents={"care": care, "virtue": {"source": "ollama",
                                                                        "model": "m"}})  # fmt: skip
    own = agent_source(
        scenario.feedback, scenario.resolve, scenario.name, "care", scenario.feedback.agents["care"]
    )
    assert own.options["hosts"] == ["http://c:3", "http://d:4"] and own.options["host"] is None
    inherited = agent_source(
        scenario.feedback,
        scenario.resolve,
        scenario.name,
        "virtue",
        scenario.feedback.agents["virtue"],
    )
    assert inherited.options["hosts"] == ["http://a:1", "http://b:2"]
    one = agent_source(
        scenario.feedback,
        scenario.resolve,
        scenario.name,
        "care",
        OllamaSpec(source="ollama", model="m", host="http://e:5"),
    )
    assert one.options["host"] == "http://e:5" and one.options["hosts"] is None
    for table, message in (
        ({**care, "host": "http://e:5"}, "sets both host and hosts"),
        ({**care, "hosts": []}, r"key hosts expects at least one server URL"),
        ({**care, "hosts": "http://c:3"}, "key hosts expects array"),
        ({**care, "hosts": ["http://c:3", "http://c:3/"]}, "the same server as item"),
    ):
        with pytest.raises(ScenarioError, match=message):
            base.replace("feedback", agents={"care": table})


# -- reporting ---------------------------------------------------------------------------
def test_figures_reach_the_summary_results_and_report(tmp_path) -> None:
    from amuled_ma.beliefs.sources.routing import RoutedSource
    from amuled_ma.deliberation.summaries import llm_server_stats, summary_lines
    from amuled_ma.evaluate.evaluator import merge_feedback
    from amuled_ma.evaluate.report.tables import servers_table

    servers = {A: Fake(), B: Fake()}
    source = pool_source(servers, concurrency=1)
    source.beliefs([req(i) for i in range(4)])
    other = OllamaSource(host=A, transport=router({A: Fake()}))
    other.beliefs([req(9)])
    with BeliefStore(tmp_path / "s.sqlite") as store:
        routed = RoutedSource({"care": CachedSource(source, store)}, CachedSource(other, store))
        figures = llm_server_stats(routed)
    # one server used by two members: counts added
    assert figures[A]["sent"] == source.server_stats()[A]["sent"] + 1
    assert figures[B]["sent"] == source.server_stats()[B]["sent"]
    assert llm_server_stats(None) == {}
    summary = {"statuses": {"ok": 5}, "agents": {}, "llm_servers": figures}
    lines = summary_lines(summary)
    assert lines[1] == "LLM servers (2):" and lines[2].startswith(f"  {A}: sent ")
    merged = merge_feedback([summary, summary])
    assert merged["llm_servers"][A]["sent"] == 2 * figures[A]["sent"]
    table = servers_table(
        Results.model_validate({"variants": {"finetune-amuled": {"feedback": merged}}})
    )
    assert table.splitlines()[0].startswith("| variant | server | sent | answered | failed |")
    assert f"| finetune-amuled | `{A}` | {2 * figures[A]['sent']} |" in table
    assert servers_table(Results.model_validate({"variants": {"base": {}}})) == ""
    assert np.isfinite(figures[A]["mean_latency_s"])
