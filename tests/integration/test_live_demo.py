"""``amuled demo`` on its own private server with the real tiny model.

The demo starts its private Ollama server (``amuled ollama up --tiny``, the new user's
path), runs the paper's FindMilk comparison on the authors' replayed recording, then its
live leg asks the tiny model about a few states and ends with where the requests' time
went, from Ollama's own metrics.

- :func:`test_demo_shows_amuled_working_and_labels_the_live_leg`: the demo as shipped: its
  report opens with every variant beside the paper; the base reaches the milk, shaping
  pacifies and wakes as the paper's, the AMULED fine-tune wakes fewer sleeping babies than
  the base, and, from the authors' published base (there when fetched or imported; without
  it the demo starts from its own), meets the paper's picture; the live leg is labelled,
  its last lines say where each live request spent its time, and on a quiet machine it
  takes under 3 minutes.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import pytest
from ollama_server_fixture import in_ci

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.cli import main
from amuled_ma.commands.demo import SUMMARY_HEADING
from amuled_ma.errors import AmuledError
from amuled_ma.servers import local_server as llm_server
from amuled_ma.servers.timing import RequestTiming

NUMBER = r"([\d,]+(?:\.\d+)?)"


def demo_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The real Ollama build and tiny model, a private server, the shared recordings."""
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
    from amuled_ma.commands.demo import fetch_inputs

    try:
        fetch_inputs("findmilk")
    except AmuledError as error:
        if in_ci():
            pytest.fail(str(error))
        pytest.skip(str(error))


#: The demo's target: under 3 minutes on this machine when it is quiet.
TARGET_S = 180.0
#: The 1-minute load average up to which the machine counts as quiet (2 cores).
QUIET_LOAD = 2.5


@pytest.mark.slow
def test_demo_shows_amuled_working_and_labels_the_live_leg(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    demo_env(tmp_path, monkeypatch)
    run_dir = tmp_path / "demo"
    load_before = os.getloadavg()[0]
    start = time.monotonic()
    code = main(["demo", "--run-dir", str(run_dir), "--no-progress"])
    wall = time.monotonic() - start
    load_after = os.getloadavg()[0]
    err = capsys.readouterr().err
    assert code == 0, err
    results = json.loads((run_dir / "results.json").read_text())["variants"]
    report = (run_dir / "report.md").read_text()

    # the base reaches the milk, sampled and greedy, in every episode
    for mode in ("sampled", "greedy"):
        assert results["base"][mode]["metrics"]["reached_milk"]["mean"] == 1.0
    # the report opens with every variant beside the paper's row
    lines = report.splitlines()
    assert lines[2] == SUMMARY_HEADING
    assert [line.split("`")[1] for line in lines[6:10]] == [
        "base", "shaped", "finetune-human", "finetune-amuled"
    ]  # fmt: skip
    # shaping: the paper's 5 / 0 at the paper's 500k base steps (3 seeds: 4.98 / 0.03)
    sampled = {name: v["sampled"]["metrics"] for name, v in results.items()}
    assert sampled["shaped"]["crying_pacified"]["mean"] >= 4.5
    assert sampled["shaped"]["sleeping_woken"]["mean"] <= 0.5
    # the AMULED fine-tune wakes fewer sleeping babies than the base: beyond the interval
    base = sampled["base"]["sleeping_woken"]
    amuled = sampled["finetune-amuled"]["sleeping_woken"]
    assert amuled["ci_high"] < base["ci_low"], (amuled, base)
    if "the fine-tunes start from the paper authors' published base policy" in lines[4]:
        # the paper's picture (docs/reproduction.md "The demo": 3 seeds, all within these)
        assert sampled["finetune-amuled"]["crying_pacified"]["mean"] >= 4.0
        assert amuled["mean"] <= 1.6
        assert sampled["finetune-amuled"]["steps_to_milk"]["mean"] <= 15.0
        human = results["finetune-human"]["greedy"]["metrics"]["reached_milk"]["mean"]
        assert human >= 0.9
    found = re.search(
        r"- AMULED \(finetune-amuled, sampled policy\) .*wakes ([\d.]+) fewer sleeping babies "
        r"than the base \(95% CI ([\d.]+) to ([\d.]+) fewer\)",
        report,
    )
    assert found, report
    assert float(found.group(1)) == pytest.approx(base["mean"] - amuled["mean"], abs=0.01)
    # the paper's row beside ours (docs/reproduction.md: 14.2 / 4.9 / 0.6), with the recipe
    row = next(line for line in lines if line.startswith("| finetune-amuled | AMULED"))
    assert "| 14.2 / 4.9 / 0.6 |" in row and row.endswith("| authors |")
    assert "the paper's main comparison" not in report.split("\n", 1)[0]
    assert "demo-sized" in report.split("\n", 1)[0]
    # the live leg: labelled, real requests through its store, each belief's source named
    heading = next(line for line in lines if line.startswith("## Live leg"))
    assert "not meaningful" in heading
    live = report[report.index(heading) :]
    assert "its moral judgement is not meaningful" in live and "ollama `amuled-tiny`" in live
    leg = json.loads((run_dir / "live" / "live.json").read_text())
    assert leg["meaningful"] is False and leg["source"] == "ollama"
    assert 1 <= leg["requests"] <= 6
    assert_timing_breakdown(err, run_dir)
    print(f"amuled demo: {wall:.0f} s, load average {load_before:.1f} -> {load_after:.1f}")
    if max(load_before, load_after) <= QUIET_LOAD:
        assert wall < TARGET_S, f"{wall:.0f} s at load {load_before:.1f}-{load_after:.1f}"


def figures(pattern: str, text: str) -> list[float]:
    """The numbers a breakdown line holds (each ``#`` of ``pattern`` is one)."""
    found = re.search(pattern.replace("#", NUMBER), text)
    assert found, f"no line matching {pattern!r} in:\n{text}"
    return [float(g.replace(",", "")) for g in found.groups()]


def assert_timing_breakdown(err: str, run_dir: Path) -> None:
    """The demo's last lines: where each live request spent its time, from Ollama's metrics."""
    assert "[demo] live requests to amuled-tiny (live leg " in err

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

    with BeliefStore(run_dir / "live" / "beliefs.sqlite", read_only=True) as store:
        rows = [row for row in store.iter_rows() if "timing" in row.extra]
    assert 1 <= len(rows) <= requests  # the live leg's requests, through its store
    for row in rows:
        timing = RequestTiming.from_dict(row.extra["timing"])
        assert timing.calls >= 1 and timing.prompt_tokens > 0 and timing.decode_tokens > 0
        assert timing.prefill_s > 0 and timing.decode_s > 0
        assert timing.prefill_s + timing.decode_s + timing.load_s <= timing.total_s + 1e-3
        assert timing.total_s <= timing.wall_s + 1e-3
