"""``amuled demo`` on its own private server with the real tiny model: the timing breakdown.

The demo starts its private Ollama server (``amuled ollama up --tiny``, the new user's
path), asks the clusters live and ends with where the requests' time went, from Ollama's
own metrics. A small budget keeps it to a few requests: two clusters, two fine-tune states,
episodes of at most four steps (so the viewer asks about few new states).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from ollama_server_fixture import in_ci

from amuled_ma import llm_server
from amuled_ma.beliefs.store import BeliefStore
from amuled_ma.beliefs.timing import RequestTiming
from amuled_ma.cli import main
from amuled_ma.errors import AmuledError

NUMBER = r"([\d,]+(?:\.\d+)?)"


def figures(pattern: str, text: str) -> list[float]:
    """The numbers a breakdown line holds (each ``#`` of ``pattern`` is one)."""
    found = re.search(pattern.replace("#", NUMBER), text)
    assert found, f"no line matching {pattern!r} in:\n{text}"
    return [float(g.replace(",", "")) for g in found.groups()]


@pytest.mark.slow
def test_demo_prints_where_each_live_request_spent_its_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        binary, gguf = llm_server.find_binary(), llm_server.find_tiny_gguf()
    except AmuledError as error:
        if in_ci():
            pytest.fail(f"the demo needs Ollama and the tiny model (CI=true): {error}")
        pytest.skip(f"the demo needs Ollama and the tiny model: {error}")
    monkeypatch.setenv("AMULED_OLLAMA_BIN", str(binary))
    monkeypatch.setenv("AMULED_TINY_GGUF", str(gguf))
    monkeypatch.setenv("AMULED_CACHE", str(tmp_path / "cache"))  # not a user's demo server
    monkeypatch.delenv("OLLAMA_HOST", raising=False)  # the demo's own private server
    run_dir = tmp_path / "demo"
    code = main(
        ["demo", "--run-dir", str(run_dir), "--no-progress",
         "--set", "base.total_steps=4096", "--set", "task.max_steps=4",
         "--set", "finetune.num_steps_per_env=2", "--set", "ppo.num_mini_batches=1",
         "--set", 'feedback.clusters=["care", "virtue"]', "--set", "evaluation.episodes=2",
         "--set", "output.tensorboard=false"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert "[demo] live requests to amuled-tiny (fine-tune " in err

    (requests, calls) = figures(r"requests # \(# chat calls", err)
    (prompt_mean, _, prefill_mean, _) = figures(
        r"prompt tokens per request: mean #, median #; prefill \(prompt eval\) mean # s, "
        r"median # s",
        err,
    )
    (decode_mean, _, decode_s_mean, _) = figures(
        r"tokens generated per request: mean #, median #; decode \(JSON schema\) mean # s, "
        r"median # s",
        err,
    )
    (sent, cache_calls, reused, _, evaluated) = figures(
        r"prefix cache: # prompt tokens sent in # calls, # reused \(#%\), # evaluated", err
    )
    (client, server, prefill, decode, load) = figures(
        r"request seconds summed: # s at the client, # s at the server = prefill # "
        r"\+ decode # \+ model load #",
        err,
    )
    assert requests >= 1 and calls >= requests
    assert prompt_mean > 1000 and decode_mean > 0  # the paper's prompt; a real reply
    assert prefill_mean > 0 and decode_s_mean > 0
    assert cache_calls >= calls and sent >= (prompt_mean - 1) * requests  # mean is rounded
    assert reused + evaluated == sent and reused > 0  # the shared prefix was reused
    assert prefill + decode + load <= server + 0.2 and server <= client + 0.2  # rounding

    with BeliefStore(run_dir / "beliefs.sqlite", read_only=True) as store:
        rows = [row for row in store.iter_rows() if "timing" in row.extra]
    assert 1 <= len(rows) <= requests  # the run's requests (the viewer's are not stored)
    for row in rows:
        timing = RequestTiming.from_dict(row.extra["timing"])
        assert timing.calls >= 1 and timing.prompt_tokens > 0 and timing.decode_tokens > 0
        assert timing.prefill_s > 0 and timing.decode_s > 0
        assert timing.prefill_s + timing.decode_s + timing.load_s <= timing.total_s + 1e-3
        assert timing.total_s <= timing.wall_s + 1e-3
