"""A person on the panel through the terminal: a real run, stopped and resumed.

Four paper clusters are replayed from the authors' recording and a sixth agent, a user
cluster, is answered by a person typing on stdin (``[feedback.agents.person] source =
"terminal"``). The first run is stopped with Ctrl-C while the person is being asked; the
answers typed so far are in the belief store, and ``--resume`` asks only new states.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from mixed_panel import TINY, mixed_scenario

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.cli import main


def _finetune(scenario: Path, run_dir: Path, iterations: int, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "amuled_ma", "finetune", str(scenario), "--run-dir", str(run_dir),
        "--no-progress", "--set", f"finetune.iterations={iterations}",
        "--set", "finetune.num_envs=1", "--set", "finetune.num_steps_per_env=4",
        "--set", "finetune.save_interval=1", "--set", "ppo.num_mini_batches=1",
        "--set", "output.tensorboard=false", *extra,
    ]  # fmt: skip


def _person_rows(run_dir: Path) -> list:
    with BeliefStore(run_dir / "beliefs.sqlite", read_only=True) as store:
        return [row for row in store.iter_rows() if row.cluster == "person"]


def test_terminal_agent_is_asked_once_per_state_and_resumes(tmp_path, recordings_dir):
    scenario = mixed_scenario(tmp_path, recordings_dir, person="terminal")
    run_dir = tmp_path / "run"
    assert main(["train", str(scenario), "--run-dir", str(run_dir), "--no-progress", *TINY]) == 0
    env = {**os.environ, "GIT_PYTHON_REFRESH": "quiet"}
    first = subprocess.Popen(
        _finetune(scenario, run_dir, 6), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        # answer three states, then leave the person silent and stop the run (Ctrl-C)
        for answer in ("0.7 0.1 0.1 0.1", "3", "0.25 0.25 0.25 0.25"):
            first.stdin.write(answer + "\n")
            first.stdin.flush()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(_rows_or_empty(run_dir)) < 3:
            time.sleep(0.2)
        time.sleep(1.0)
        first.send_signal(signal.SIGINT)
        _, err = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 130, err
    assert "resume with: amuled finetune" in err and "Traceback" not in err
    answered = [r for r in _person_rows(run_dir) if r.status == "ok"]
    assert len(answered) == 3
    assert sorted(r.belief.tolist() for r in answered) == sorted(
        [[0.7, 0.1, 0.1, 0.1], [0.0, 0.0, 0.0, 1.0], [0.25, 0.25, 0.25, 0.25]]
    )
    asked_before = {tuple(r.obs) for r in answered}

    # resume: every later state gets the same answer; the three answered are not asked again
    resume = subprocess.run(
        _finetune(scenario, run_dir, 6, "--resume"), input="1\n" * 200, capture_output=True,
        text=True, env=env, timeout=300,
    )  # fmt: skip
    assert resume.returncode == 0, resume.stderr
    rows = [r for r in _person_rows(run_dir) if r.status == "ok"]
    later = [r for r in rows if tuple(r.obs) not in asked_before]
    assert later and all(r.belief.tolist() == [0.0, 1.0, 0.0, 0.0] for r in later)
    asked_again = resume.stderr.count("belief> ")
    assert asked_again == len(later)  # one prompt per new state, none for the three
    feedback = json.loads((run_dir / "finetune-amuled" / "feedback.json").read_text())
    assert feedback["agents"]["person"]["ok"] > 0


def _rows_or_empty(run_dir: Path) -> list:
    try:
        return [r for r in _person_rows(run_dir) if r.status == "ok"]
    except Exception:
        return []
