"""Faults of a real Ollama server, each provoked for real: not running, ``kill -9``, slow, no model.

The belief path must turn each into either a clear, fast error (nothing to retry) or
bounded, counted retries and fallbacks (the run goes on), and never lose an answer that
already arrived.
"""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from _live_helpers import OPTIONS, TASKS, DelayProxy, wait_until

from amuled_ma.beliefs import BeliefRequest, ScriptedSource
from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.errors import BackendUnavailable, ModelNotFound
from amuled_ma.servers import local_server as llm_server


def _requests(n: int, task: str = "driving") -> list[BeliefRequest]:
    """``n`` distinct short requests (a short prompt keeps the tiny model fast)."""
    spec = TASKS[task]
    return [
        BeliefRequest(
            task=task,
            cluster=f"probe{i}",
            obs=(float(i),),
            action_names=spec["actions"],
            messages=(
                ("system", "Answer with one probability per action as JSON."),
                ("user", f"State {i}. {spec['state'][-200:]}"),
            ),
        )
        for i in range(n)
    ]


def _source(host: str, model: str, **kwargs: object) -> OllamaSource:
    options = {
        "reasoning": False,
        "num_ctx": OPTIONS["num_ctx"],
        "num_predict": OPTIONS["num_predict"],
        "concurrency": 2,
        **kwargs,
    }
    return OllamaSource(model, host=host, **options)  # type: ignore[arg-type]


def test_server_not_running_is_a_clear_error_within_5_s(tmp_path: Path) -> None:
    host = f"http://127.0.0.1:{llm_server.free_port()}"
    source = _source(host, llm_server.TINY_MODEL)
    store_path = tmp_path / "beliefs.sqlite"
    start = time.monotonic()
    with pytest.raises(BackendUnavailable) as info, BeliefStore(store_path) as store:
        CachedSource(source, store).beliefs(_requests(3))
    elapsed = time.monotonic() - start
    source.close()
    assert elapsed < 5.0, f"took {elapsed:.1f} s"
    message = str(info.value)
    assert host in message and "amuled ollama up" in message
    with BeliefStore(store_path) as store:
        assert len(store) == 0, "nothing is written"
    assert source.stats.attempts == 0, "nothing is sent before the server answers"


def test_model_missing_names_the_model_and_the_create_command(ollama_host: str) -> None:
    source = _source(ollama_host, "no-such-model:7b")
    with pytest.raises(ModelNotFound) as info:
        source.beliefs(_requests(1))
    assert "'no-such-model:7b'" in str(info.value)
    assert "ollama pull no-such-model:7b" in str(info.value)
    source.close()

    # A fresh server without the tiny model: the hint is the command that registers it.
    bare = llm_server.OllamaServer()
    bare.start()
    try:
        tiny = _source(bare.host, llm_server.TINY_MODEL)
        with pytest.raises(ModelNotFound) as info:
            tiny.beliefs(_requests(1))
        tiny.close()
        assert "'amuled-tiny'" in str(info.value)
        assert "amuled ollama up --tiny" in str(info.value)
        assert "ollama create amuled-tiny" in str(info.value)
    finally:
        bare.stop()


def test_slower_than_timeout_counts_timeouts_and_uses_the_fallback(
    ollama_host: str, ollama_model: str
) -> None:
    """A loopback proxy delays every connection by 3 s; the request timeout is 1 s."""
    port = int(llm_server.normalize_host(ollama_host).rsplit(":", 1)[1])
    fallback = ScriptedSource({"*": [1.0, 0.0, 0.0]}, label="fallback-straight")
    requests = _requests(4)
    with DelayProxy(port, delay=3.0) as proxy:
        source = _source(
            proxy.host, ollama_model, timeout_s=1.0, retries=1, retry_timeouts=False,
            check_timeout_s=4.5, fallback=fallback,
        )  # fmt: skip
        start = time.monotonic()
        results = source.beliefs(requests)
        elapsed = time.monotonic() - start
        source.close()
    assert source.stats.timeouts == len(requests), source.stats
    assert source.stats.fallbacks == len(requests)
    assert source.stats.retries == 0, "timeouts are not retried unless retry_timeouts"
    for result in results:
        assert result.source == "scripted" and result.extra["ollama_failure"] == "timeout"
        assert np.array_equal(result.belief, [1.0, 0.0, 0.0])
    # 3 s to pass the check through the proxy, then 2 rounds of 1 s timeouts (concurrency 2).
    assert elapsed < 3.0 + 2 * 1.0 + 4.0, f"took {elapsed:.1f} s"


def test_slower_than_timeout_with_retries_backs_off_then_falls_back(
    ollama_host: str, ollama_model: str
) -> None:
    port = int(llm_server.normalize_host(ollama_host).rsplit(":", 1)[1])
    with DelayProxy(port, delay=3.0) as proxy:
        source = _source(
            proxy.host, ollama_model, timeout_s=0.5, retries=2, retry_timeouts=True,
            backoff_s=0.2, check_timeout_s=4.5, concurrency=1,
        )  # fmt: skip
        start = time.monotonic()
        [result] = source.beliefs(_requests(1))
        elapsed = time.monotonic() - start
        source.close()
    assert result.status == "timeout" and np.allclose(result.belief, 1 / 3)
    assert source.stats.timeouts == 3 and source.stats.retries == 2
    # check (3 s) + 3 attempts x 0.5 s + backoff 0.2 + 0.4 s
    assert 3.0 + 1.5 + 0.6 - 0.1 <= elapsed < 3.0 + 1.5 + 0.6 + 3.0, f"took {elapsed:.1f} s"


@pytest.mark.slow
def test_kill_9_mid_run_retries_with_backoff_then_resumes_without_asking_again(
    private_ollama_server, tmp_path: Path
) -> None:
    """A real ``kill -9`` of ``ollama serve`` while a batch is in flight.

    The source retries a bounded number of times with exponential backoff, then raises
    BackendUnavailable; the answers that arrived before are in the store. A new server on
    the same port and model directory finishes the batch, sending only the rest.
    """
    server = private_ollama_server()
    port = int(server.host.rsplit(":", 1)[1])
    model = llm_server.TINY_MODEL
    requests = _requests(12)
    store_path = tmp_path / "beliefs.sqlite"
    source = _source(server.host, model, retries=3, backoff_s=0.25, backoff_max_s=1.0)
    outcome: dict[str, object] = {}

    def run() -> None:
        with BeliefStore(store_path) as store:
            try:
                CachedSource(source, store).beliefs(requests)
            except BaseException as error:
                outcome["error"] = error
            outcome["end"] = time.monotonic()

    worker = threading.Thread(target=run)
    worker.start()
    assert wait_until(lambda: source.stats.ok + source.stats.repaired >= 3, timeout=120)
    killed_at = time.monotonic()
    assert server.pid is not None
    server.kill(signal.SIGKILL)  # kill -9 the server and its runner
    worker.join(timeout=60)
    assert not worker.is_alive()
    error = outcome.get("error")
    assert isinstance(error, BackendUnavailable), repr(error)
    assert server.host in str(error) and "amuled ollama up" in str(error)
    # Bounded: retries with 0.25 + 0.5 + 1.0 s backoff, then give up.
    assert source.stats.retries >= 3
    assert float(outcome["end"]) - killed_at < 0.25 + 0.5 + 1.0 + 10.0  # type: ignore[arg-type]
    source.close()
    with BeliefStore(store_path) as store:
        answered_before = len(
            [k for k in CachedSource(source, store).keys(requests) if store.get(k) is not None]
        )
    assert 3 <= answered_before < len(requests)

    # Restart on the same port with the same model directory, then resume.
    server.stop()
    restarted = llm_server.OllamaServer(workdir=server.workdir, port=port)
    restarted.start()
    try:
        resumed_source = _source(restarted.host, model)
        with BeliefStore(store_path) as store:
            cached = CachedSource(resumed_source, store)
            results = cached.beliefs(requests)
        resumed_source.close()
    finally:
        restarted.stop()
    assert cached.stats.hits == answered_before
    assert resumed_source.stats.sent == len(requests) - answered_before
    assert all(r.belief.shape == (3,) for r in results)


def _train_base(run_dir: Path) -> None:
    from amuled_ma.cli import main

    args = ["train", "findmilk", "--run-dir", str(run_dir), "--variant", "base", "--no-progress"]
    args += ["--set", "base.total_steps=2048", "--set", "output.tensorboard=false"]
    assert main(args) == 0


def _finetune_against_nothing(run_dir: Path) -> tuple[int, float]:
    from amuled_ma.cli import main

    host = f"http://127.0.0.1:{llm_server.free_port()}"
    args = ["finetune", "findmilk", "--run-dir", str(run_dir), "--feedback", "cluster:care"]
    for setting in (
        'feedback.source="ollama"',
        f'feedback.model="{llm_server.TINY_MODEL}"',
        f'feedback.host="{host}"',
        "finetune.iterations=2",
        "output.tensorboard=false",
    ):
        args += ["--set", setting]
    start = time.monotonic()
    code = main([*args, "--no-progress"])
    return code, time.monotonic() - start


def test_cli_finetune_without_server_fails_fast_and_clearly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run_dir = tmp_path / "run"
    _train_base(run_dir)
    capsys.readouterr()
    code, elapsed = _finetune_against_nothing(run_dir)
    err = capsys.readouterr().err
    assert code == 1
    assert elapsed < 5.0, f"took {elapsed:.1f} s"
    assert "no Ollama server answers at http://127.0.0.1:" in err and "amuled ollama up" in err
    assert not (run_dir / "finetune-cluster-care" / "model_last.pt").exists()


def test_cli_finetune_without_server_writes_nothing(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    _train_base(run_dir)
    before = sorted(p for p in run_dir.rglob("*") if p.is_file())
    code, _ = _finetune_against_nothing(run_dir)
    assert code == 1
    assert sorted(p for p in run_dir.rglob("*") if p.is_file()) == before
