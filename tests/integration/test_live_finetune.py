"""``amuled finetune`` with live feedback from the tiny model on a real Ollama server.

A few PPO iterations on FindMilk from a briefly trained base policy, the care cluster
asked live (one cluster keeps the tiny-model cost to a few requests). The second run of
the same job finds every answer in the run's belief store and sends no chat request.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _live_helpers import DelayProxy

from amuled_ma import llm_server
from amuled_ma.beliefs.store import BeliefStore
from amuled_ma.cli import main


def _finetune(run_dir: Path, host: str, model: str, *extra: str) -> int:
    settings = {
        "feedback.source": '"ollama"',
        "feedback.model": f'"{model}"',
        "feedback.host": f'"{host}"',
        "feedback.concurrency": "1",
        "feedback.timeout_s": "300.0",
        "finetune.iterations": "2",
        "finetune.num_envs": "1",
        "finetune.num_steps_per_env": "2",
        "finetune.save_interval": "1",
        "output.tensorboard": "false",
    }
    args = ["finetune", "findmilk", "--run-dir", str(run_dir), "--feedback", "cluster:care"]
    for key, value in settings.items():
        args += ["--set", f"{key}={value}"]
    return main([*args, "--no-progress", *extra])


@pytest.mark.slow
def test_finetune_with_live_feedback_then_all_from_the_store(
    ollama_host: str, ollama_model: str, tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    base = [
        "train", "findmilk", "--run-dir", str(run_dir), "--variant", "base", "--no-progress",
        "--set", "base.total_steps=4096", "--set", "output.tensorboard=false",
    ]  # fmt: skip
    assert main(base) == 0

    assert _finetune(run_dir, ollama_host, ollama_model) == 0
    out = run_dir / "finetune-cluster-care"
    if not out.is_dir():  # folder naming belongs to the learner; find it
        [out] = [p for p in run_dir.iterdir() if p.name.startswith("finetune")]
    summary = json.loads((out / "feedback.json").read_text())
    assert summary["steps"] == 4 and summary["unique_states"] >= 1
    assert sum(summary["statuses"].values()) >= summary["unique_states"]
    assert (out / "model_last.pt").is_file()
    with BeliefStore(run_dir / "beliefs.sqlite") as store:
        rows = len(store)
    assert rows >= summary["unique_states"]

    # Same job again (--force), through a request-counting proxy: every belief is a hit.
    port = int(llm_server.normalize_host(ollama_host).rsplit(":", 1)[1])
    with DelayProxy(port, delay=0.0) as proxy:
        assert _finetune(run_dir, proxy.host, ollama_model, "--force") == 0
    assert not [r for r in proxy.requests if r == "POST /api/chat"], proxy.requests
    with BeliefStore(run_dir / "beliefs.sqlite") as store:
        assert len(store) == rows
