"""The preflight's live cost, measured on this machine, against the tiny model's real time.

A fine-tune's panel with one member asked live (``care`` on the tiny Ollama model): the
preflight's line (`live_costs`) times one request after a warm-up; then the fine-tune's own
feedback asks about new states, and the seconds each took must be within a factor of 2 of
the estimate. Once the store holds enough timed requests, the line quotes their median.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from scenario_feedback import make_feedback

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.keys import request_key
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult
from amuled_ma.deliberation.build import MIN_TIMED_REQUESTS, live_costs
from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.scenario import scenario_from_dict
from amuled_ma.tasks import make_batched

pytestmark = pytest.mark.ollama

PER_REQUEST = re.compile(r": ([0-9.]+) s a request \(([^)]*)\)")


def _scenario(tmp_path: Path, host: str, model: str):
    return scenario_from_dict(
        {
            "task": {"name": "findmilk"},
            "feedback": {
                "source": "rules",
                "clusters": ["care", "virtue"],
                "store": str(tmp_path / "beliefs.sqlite"),
                "agents": {
                    "care": {
                        "source": "ollama",
                        "model": model,
                        "host": host,
                        "num_ctx": 4096,
                        "num_predict": 48,
                        "reasoning": False,
                        "concurrency": 1,
                        "timeout_s": 900.0,
                    }
                },
            },
        }
    )


@pytest.mark.slow
def test_estimate_within_a_factor_of_2_of_the_measured_time(
    tmp_path: Path, ollama_host: str, ollama_model: str
) -> None:
    torch.set_num_threads(1)
    scenario = _scenario(tmp_path, ollama_host, ollama_model)
    said: list[str] = []
    (line,) = live_costs(plan_panel("amuled", scenario), scenario.store_path(tmp_path), said.append)
    assert said and "timing a request to" in said[0]  # the wait is announced
    match = PER_REQUEST.search(line)
    assert match is not None, line
    estimate = float(match.group(1))
    assert match.group(2) == "measured here: 1 request timed after a warm-up"
    assert line.startswith(f"live feedback: care asked of {ollama_model}:")
    assert "per new state the fine-tune visits" in line  # no integer budget

    # the fine-tune's feedback asks care live about states the probe did not see
    feedback = make_feedback("amuled", scenario, tmp_path)
    task = make_batched("findmilk", 1, seed=3)
    task.reset()
    times = []
    for action in (3, 3, 0):  # right, right, up: three new states
        task.step(torch.tensor([action]))
        start = time.perf_counter()
        feedback(task.obs, task)
        times.append(time.perf_counter() - start)
    feedback.close()
    measured = float(np.mean(times))
    assert estimate / 2 <= measured <= estimate * 2, (estimate, times)


def test_the_stores_recorded_times_replace_the_probe(
    tmp_path: Path, ollama_host: str, ollama_model: str
) -> None:
    """Recorded requests of 2, 3, 9, 4, 40 s: the line quotes their median, 4 s, no probe."""
    ident = {"source": "ollama", "model": ollama_model, "digest": "sha256:x", "options": {}}
    items = []
    for i, seconds in enumerate([2.0, 3.0, 9.0, 4.0, 40.0]):
        request = BeliefRequest("findmilk", "care", (float(i),), ("u", "d", "l", "r"))
        result = BeliefResult(np.ones(4) / 4, "ok", "ollama", raw="{}", latency_s=seconds)
        items.append((request_key(ident, request), ident, request, result))
    with BeliefStore(tmp_path / "beliefs.sqlite") as store:
        store.put_many(items)
    said: list[str] = []
    scenario = _scenario(tmp_path, ollama_host, ollama_model)
    (line,) = live_costs(plan_panel("amuled", scenario), scenario.store_path(tmp_path), said.append)
    assert said == []
    assert f"4.0 s a request (measured here: median of {MIN_TIMED_REQUESTS} recorded" in line
