"""The shipped mixed panel (examples/mixed_panel.toml) finishes, a person answering on a budget.

The example as shipped, but for its live member: social justice is replayed here instead
of asked to Ollama (no server in the tests), and the person at the terminal is a scripted
stdin, as in ``tests/learn/test_terminal_agent_run.py``. Its ``[feedback.distill]`` budget
bounds the person's answers: the run finishes its 20 iterations with at most that many.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from mixed_panel import TINY

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.cli import main
from amuled_ma.scenario import load_scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _example_without_ollama(tmp_path: Path) -> Path:
    """examples/mixed_panel.toml with social justice replayed and absolute paths."""
    text = (EXAMPLES / "mixed_panel.toml").read_text()
    start = text.index("[feedback.agents.social_justice]")
    end = text.index("[feedback.agents.animal_welfare]")
    text = text[:start] + '[feedback.agents.social_justice]\nsource = "replay"\n\n' + text[end:]
    text = text.replace(
        'clusters_dirs = ["my_clusters"]', f'clusters_dirs = ["{EXAMPLES / "my_clusters"}"]'
    )
    path = tmp_path / "mixed_panel.toml"
    path.write_text(text)
    return path


def test_shipped_mixed_panel_finishes_with_the_budget_of_answers(
    tmp_path, recordings_dir, monkeypatch
):
    monkeypatch.setenv("AMULED_RECORDINGS", str(recordings_dir))
    shipped = load_scenario(EXAMPLES / "mixed_panel.toml")
    budget = shipped.feedback.distill.budget
    assert shipped.feedback.distill.enabled and isinstance(budget, int) and budget <= 20
    scenario = _example_without_ollama(tmp_path)
    run_dir = tmp_path / "run"
    assert main(["train", str(scenario), "--run-dir", str(run_dir), "--no-progress", *TINY]) == 0
    env = {**os.environ, "GIT_PYTHON_REFRESH": "quiet", "AMULED_RECORDINGS": str(recordings_dir)}
    argv = [
        sys.executable, "-m", "amuled_ma", "finetune", str(scenario), "--run-dir", str(run_dir),
        "--name", "mixed-panel", "--no-progress",
    ]  # fmt: skip
    start = time.perf_counter()
    done = subprocess.run(
        argv, input="1\n" * 200, capture_output=True, text=True, env=env, timeout=900
    )
    seconds = time.perf_counter() - start
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    with BeliefStore(run_dir / "beliefs.sqlite", read_only=True) as store:
        person = [r for r in store.iter_rows() if r.cluster == "animal_welfare"]
    assert 1 <= len(person) <= budget  # the person answered the budget's states only
    assert all(r.status == "ok" and r.belief.tolist() == [0.0, 1.0, 0.0, 0.0] for r in person)
    assert (run_dir / "finetune-mixed-panel" / "model_last.pt").is_file()
    assert f"asked {len(person)} of" in done.stdout  # the output states the answers asked
    # each question says where the person is in the budget's questions, with the state's grid
    questions = [line for line in done.stderr.splitlines() if line.startswith("== human: ")]
    assert len(questions) == len(person)
    assert all(q.endswith(f"state {k} of {budget} ==") for k, q in enumerate(questions, 1))
    assert "      0 1 2 3 4 5 6 7  = x" in done.stderr
    print(f"mixed panel: {len(person)} answers, fine-tune in {seconds:.0f} s")
