"""One writer per run folder, and SIGTERM keeps the work: real processes, real signals."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from amuled_ma.cli import main
from amuled_ma.files.run_lock import LOCK_NAME, RunFolderBusy, run_folder_lock
from amuled_ma.learn.checkpoints import checkpoint_infos

AMULED = [sys.executable, "-m", "amuled_ma"]
ENV = {**os.environ, "GIT_PYTHON_REFRESH": "quiet"}
#: 16 x 16 transitions per iteration; save_interval 1000 so that only a stop checkpoints early
LONG = [
    "--set", "base.total_steps=100_000_000",
    "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16",
    "--set", "base.save_interval=1000",
    "--set", "output.tensorboard=false",
    "--no-progress",
]  # fmt: skip


def _start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [*AMULED, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV
    )


def _wait_for_lock(run_dir: Path, proc: subprocess.Popen, timeout: float = 60) -> dict:
    """Wait until ``proc`` holds the run folder's lock and has started training."""
    lock = run_dir / LOCK_NAME
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        if lock.is_file() and lock.read_text() and (run_dir / "base" / "config.json").is_file():
            return json.loads(lock.read_text())
        time.sleep(0.1)
    raise AssertionError("the first run never took the lock")


def test_second_writer_is_refused_then_sigterm_checkpoints_and_resumes(tmp_path, capsys):
    run_dir = tmp_path / "run"
    first = _start(["train", "findmilk", "--run-dir", str(run_dir), *LONG])
    try:
        holder = _wait_for_lock(run_dir, first)
        assert holder["pid"] == first.pid and "train findmilk" in holder["command"]

        # a second writer: refused at once, naming the holder; nothing of the first touched
        config_before = (run_dir / "base" / "config.json").read_text()
        started = time.perf_counter()
        assert main(["train", "findmilk", "--run-dir", str(run_dir), "--force", *LONG]) == 1
        assert time.perf_counter() - started < 5
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert f"pid {first.pid}" in err and "train findmilk" in err and "--run-dir" in err
        assert (run_dir / "base" / "config.json").read_text() == config_before
        for command in (["evaluate", str(run_dir)], ["run", "findmilk", "--run-dir", str(run_dir)]):
            assert main(command) == 1
            assert f"pid {first.pid}" in capsys.readouterr().err

        time.sleep(2.0)  # let it iterate: SIGTERM must keep those iterations
        first.send_signal(signal.SIGTERM)
        out, err = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 143, (out, err)
    assert "terminated (SIGTERM)" in err and "checkpoint written" in err, err
    assert "resume with: amuled train findmilk" in err and "Traceback" not in err, err
    state = checkpoint_infos(run_dir / "base" / "model_last.pt")
    done = state["iteration"]
    assert 0 < done < 1000 and not state["completed"]  # before any periodic save

    # the lock went with the process; resume to 2 more iterations
    steps = (done + 2) * 256
    resume = ["train", "findmilk", "--run-dir", str(run_dir), "--resume", *LONG]
    assert main([*resume, "--set", f"base.total_steps={steps}"]) == 0
    assert checkpoint_infos(run_dir / "base" / "model_last.pt")["iteration"] == done + 2


def test_lock_is_reentrant_in_one_process_and_exclusive_across(tmp_path):
    folder = tmp_path / "f"
    code = (
        "import sys; from amuled_ma.files.run_lock import run_folder_lock\n"
        "with run_folder_lock(sys.argv[1], 'amuled other'):\n"
        "    print('held', flush=True); sys.stdin.read()\n"
    )
    with run_folder_lock(folder, "amuled me"), run_folder_lock(folder, "amuled me again"):
        other = subprocess.run(
            [sys.executable, "-c", code, str(folder)], capture_output=True, text=True, input=""
        )
        assert other.returncode == 1 and "RunFolderBusy" in other.stderr
        assert f"pid {os.getpid()}" in other.stderr and "amuled me" in other.stderr
    holder = subprocess.Popen(
        [sys.executable, "-c", code, str(folder)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        try:
            with run_folder_lock(folder, "amuled me"):
                raise AssertionError("two holders at once")
        except RunFolderBusy as busy:
            assert f"pid {holder.pid}" in str(busy) and "amuled other" in str(busy)
        holder.kill()  # kill -9: the kernel drops the lock with the process
        holder.wait(timeout=30)
        with run_folder_lock(folder, "amuled me"):
            pass
    finally:
        if holder.poll() is None:
            holder.kill()
