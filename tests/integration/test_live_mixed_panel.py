"""A mixed panel fine-tunes against the real server: replay, the tiny model and a person.

Four paper clusters are replayed from the authors' recording, ``social_justice`` is asked
live to the tiny model on a real Ollama server, and a user cluster ``person`` is answered
by a script typing on the command's stdin (``source = "terminal"``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from mixed_panel import TINY, mixed_scenario

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.cli import main


@pytest.mark.slow
def test_mixed_panel_fine_tunes_with_replay_ollama_and_terminal(
    ollama_host: str, ollama_model: str, recordings_dir, tmp_path
) -> None:
    live = {"source": "ollama", "model": ollama_model, "host": ollama_host,
            "concurrency": 1, "timeout_s": 300.0}  # fmt: skip
    scenario = mixed_scenario(
        tmp_path, recordings_dir, person="terminal", agents={"social_justice": live}
    )
    run_dir = tmp_path / "run"
    assert main(["train", str(scenario), "--run-dir", str(run_dir), "--no-progress", *TINY]) == 0
    finetune = [
        sys.executable, "-m", "amuled_ma", "finetune", str(scenario), "--run-dir", str(run_dir),
        "--no-progress", "--set", "finetune.iterations=2", "--set", "finetune.num_envs=1",
        "--set", "finetune.num_steps_per_env=2", "--set", "ppo.num_mini_batches=1",
        "--set", "output.tensorboard=false",
    ]  # fmt: skip
    done = subprocess.run(
        finetune, input="0.1 0.2 0.3 0.4\n" * 50, capture_output=True, text=True, timeout=900,
        env={**os.environ, "GIT_PYTHON_REFRESH": "quiet"},
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    with BeliefStore(run_dir / "beliefs.sqlite", read_only=True) as store:
        rows = list(store.iter_rows())
    by_agent: dict[str, set[str]] = {}
    for row in rows:
        by_agent.setdefault(row.cluster, set()).add(row.source)
    assert by_agent["person"] == {"terminal"}
    assert by_agent["social_justice"] == {"ollama"}
    person = [r for r in rows if r.cluster == "person"]
    assert person and all(r.belief.tolist() == [0.1, 0.2, 0.3, 0.4] for r in person)
    live_rows = [r for r in rows if r.cluster == "social_justice"]
    assert live_rows and all(r.identity.get("model") == ollama_model for r in live_rows)
    # the four replayed clusters are not in the store under another source
    assert "replay" not in by_agent.get("person", set())
    feedback = json.loads((run_dir / "finetune-amuled" / "feedback.json").read_text())
    agents = feedback["agents"]
    assert set(agents) == {"consequentialist", "deontological", "virtue", "care",
                           "social_justice", "person"}  # fmt: skip
    assert agents["person"]["ok"] == feedback["steps"]  # the person answered every step
    assert agents["consequentialist"]["ok"] == feedback["steps"]
