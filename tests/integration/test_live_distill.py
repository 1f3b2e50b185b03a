"""A distilled fine-tune on a budget with the tiny model on a real Ollama server.

Two clusters asked live about at most 2 distinct states (``budget = 2``), the distilled
model answering every other state: the requests sent stay within the budget, and the
run's belief store holds exactly the asked states' answers, one row per cluster (the
model's answers are never stored).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.cli import main

CLUSTERS = ("care", "virtue")
BUDGET = 2


@pytest.mark.slow
def test_a_live_distilled_fine_tune_asks_only_its_budget(
    ollama_host: str, ollama_model: str, tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    common = ["--run-dir", str(run_dir), "--no-progress", "--set", "output.tensorboard=false"]
    base = ["train", "findmilk", "--variant", "base", "--set", "base.total_steps=4096"]
    assert main([*base, *common]) == 0
    finetune = [
        "finetune", "findmilk", "--feedback", "amuled", *common,
        "--set", 'feedback.source="ollama"', "--set", f'feedback.model="{ollama_model}"',
        "--set", f'feedback.host="{ollama_host}"', "--set", "feedback.concurrency=1",
        "--set", "feedback.timeout_s=300.0",
        "--set", "feedback.ollama={reasoning = false, num_predict = 128}",
        "--set", f"feedback.clusters={json.dumps(list(CLUSTERS))}",
        "--set", "feedback.distill.enabled=true", "--set", f"feedback.distill.budget={BUDGET}",
        "--set", "finetune.iterations=2", "--set", "finetune.num_envs=2",
        "--set", "finetune.num_steps_per_env=4", "--set", "ppo.num_mini_batches=2",
    ]  # fmt: skip
    assert main(finetune) == 0
    folder = run_dir / "finetune-amuled"
    distill = json.loads((folder / "feedback.json").read_text())["distill"]
    ledger = json.loads((folder / "distill.json").read_text())
    asked = ledger["ledger"]["asked"]
    assert len(asked) == distill["asked_states"] <= BUDGET
    assert distill["visited_states"] > len(asked)  # the model answered the others
    assert distill["model_states"] == distill["visited_states"] - len(asked)
    # requests sent within the budget: one per cluster and asked state at most
    assert 1 <= distill["requests_sent"] <= BUDGET * len(CLUSTERS)
    # the store holds exactly the asked states, one row per cluster
    asked_obs = {tuple(ledger["asked_obs"][key]) for key in asked}
    with BeliefStore(run_dir / "beliefs.sqlite") as store:
        rows = list(store.iter_rows())
    assert len(rows) == len(asked) * len(CLUSTERS) == distill["requests_sent"]
    assert {tuple(row.obs) for row in rows} == asked_obs
    assert {row.cluster for row in rows} == set(CLUSTERS)
