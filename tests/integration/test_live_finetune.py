"""``amuled finetune`` with live feedback from the tiny model on a real Ollama server.

A few PPO iterations on FindMilk from a briefly trained base policy, the care cluster
asked live (one cluster keeps the tiny-model cost to a few requests). The server is killed
with a real ``kill -9`` mid-run; after a restart ``--resume`` finishes the job, and a
third run of the same job finds every answer in the run's belief store (no chat request).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _live_helpers import DelayProxy, wait_until

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.servers import local_server as llm_server


@pytest.mark.slow
def test_finetune_survives_kill_9_of_the_server_and_resumes(
    private_ollama_server, ollama_model: str, tmp_path: Path
) -> None:
    """``kill -9`` of the server mid-run: the run stops with a clear error after bounded
    retries, its last checkpoint stays; after a restart, ``--resume`` finishes the job and
    no belief already answered is asked again."""
    if ollama_model != llm_server.TINY_MODEL:
        pytest.skip("needs the tiny model on a private server")
    server = private_ollama_server()
    port = int(server.host.rsplit(":", 1)[1])
    run_dir = tmp_path / "run"
    base = [
        sys.executable, "-m", "amuled_ma.cli", "train", "findmilk", "--run-dir", str(run_dir),
        "--variant", "base", "--no-progress", "--set", "base.total_steps=4096",
        "--set", "output.tensorboard=false",
    ]  # fmt: skip
    subprocess.run(base, check=True, capture_output=True)
    finetune = [
        sys.executable, "-m", "amuled_ma.cli", "finetune", "findmilk", "--run-dir", str(run_dir),
        "--feedback", "cluster:care", "--no-progress",
        "--set", 'feedback.source="ollama"', "--set", f'feedback.model="{ollama_model}"',
        "--set", f'feedback.host="{server.host}"', "--set", "feedback.concurrency=1",
        "--set", "feedback.timeout_s=300.0", "--set", "finetune.iterations=4",
        "--set", "finetune.num_envs=1", "--set", "finetune.num_steps_per_env=2",
        "--set", "finetune.save_interval=1", "--set", "output.tensorboard=false",
        "--set", "ppo.num_mini_batches=1",  # 2 transitions per iteration: one mini-batch
    ]  # fmt: skip
    checkpoint = run_dir / "finetune-cluster-care" / "model_last.pt"
    job = subprocess.Popen(finetune, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert wait_until(checkpoint.is_file, timeout=400), "no checkpoint after iteration 1"
        server.kill(signal.SIGKILL)  # kill -9: server and model runner
        killed_at = time.monotonic()
        output, _ = job.communicate(timeout=120)
    finally:
        if job.poll() is None:
            job.kill()
            job.wait()
    assert job.returncode == 1, output
    assert time.monotonic() - killed_at < 60
    assert "no Ollama server answers at" in output and "amuled ollama up" in output
    assert "checkpoint written to" in output and "resume with: amuled finetune findmilk" in output
    assert checkpoint.is_file()
    with BeliefStore(run_dir / "beliefs.sqlite") as store:
        answered = sum(i["answers"] for i in store.identities())  # cacheable (ok/repaired)
    assert answered >= 1

    server.stop()
    restarted = llm_server.OllamaServer(workdir=server.workdir, port=port)
    restarted.start()
    try:
        with DelayProxy(port, delay=0.0) as proxy:
            resume = [a.replace(server.host, proxy.host) for a in finetune] + ["--resume"]
            done = subprocess.run(resume, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stdout + done.stderr
        summary = json.loads((checkpoint.parent / "feedback.json").read_text())
        with BeliefStore(run_dir / "beliefs.sqlite") as store:
            total = len(store)
        # Only beliefs never answered before were asked after the restart: at most
        # 1 + parse_retries (1) chat calls each.
        chats = len([r for r in proxy.requests if r == "POST /api/chat"])
        assert chats <= 2 * (total - answered), (chats, total, answered)
        assert summary["steps"] >= 2 and summary["unique_states"] >= 1

        # The same job from scratch (--force), twice. An interrupted + resumed run does not
        # replay the RNG of an uninterrupted one, so the first rerun may meet new states;
        # the second meets exactly the first's: every answered belief comes from the store,
        # only abstained replies (never served from the store) may be asked again.
        rerun = [*finetune, "--force"]
        done = subprocess.run(rerun, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stdout + done.stderr
        with BeliefStore(run_dir / "beliefs.sqlite") as store:
            unanswered = len(store) - sum(i["answers"] for i in store.identities())
        with DelayProxy(port, delay=0.0) as again:
            rerun = [a.replace(server.host, again.host) for a in finetune] + ["--force"]
            done = subprocess.run(rerun, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stdout + done.stderr
        rechats = len([r for r in again.requests if r == "POST /api/chat"])
        assert rechats <= 2 * unanswered, (again.requests, unanswered)
        assert (checkpoint.parent / "model_last.pt").is_file()
    finally:
        restarted.stop()
