"""SIGTERM during Ray's start, many times: every one must exit 143 with one line.

``python tools/sigterm_ray_start.py [--count 100] [--work DIR]`` runs ``amuled run findmilk
--jobs 2`` (a local Ray) ``--count`` times inside fresh network and PID namespaces
(``unshare -n -p -f --kill-child --mount-proc``: loopback only, so nothing leaves the
machine and Ray cannot pick an external interface; and this script's Ray processes alone
in sight). Each time it waits until the driver has started the local Ray's
``gcs_server``, waits a further delay spread over Ray's start (0 to ``--spread``
seconds, by the golden-ratio sequence, so the first runs already cover that time), sends
SIGTERM to the driver alone, and records its exit status (``hang`` when it has not exited within
``--wait`` seconds; it is then killed), whether its stderr is the one line
``amuled: terminated (SIGTERM)`` (Ray's C++ core warning about a missing route out,
which Ray prints before its logger is set, set aside), whether a run folder (more than its
lock) was left, which of Ray's processes outlived the driver by 3 s (then ended, before the
next run), and of a run that hangs, every thread's Python stack (``py-spy dump``, when
installed).

Prints one line per run and a summary of the exit-status counts; exits 0 when every run
exited 143, and each whose SIGTERM came before the driver wrote its run folder (that is,
during Ray's start) with the one line and no folder; a SIGTERM after that stops the run as
Ctrl-C does (checkpoints, ``resume with: ...``). Needs root (or ``CAP_SYS_ADMIN``) for the
namespaces. Not part of the test suite: it takes about 10 s a run.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OWN_NAMESPACES = ["unshare", "-n", "-p", "-f", "--kill-child", "--mount-proc"]
TINY = [
    "--episodes", "1", "--no-progress",
    "--set", "base.total_steps=1024", "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16", "--set", "finetune.num_envs=4",
    "--set", "finetune.num_steps_per_env=8", "--set", "finetune.iterations=3",
    "--set", "output.tensorboard=false", "--set", 'feedback.source="rules"',
]  # fmt: skip
#: Ray's C++ core warning, printed by Ray before its logger reads any setting.
RAY_CORE_LOG = re.compile(r"^\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} [WI] \d+ \d+\] \w+\.cc:\d+: ")
ONE_LINE = ["amuled: terminated (SIGTERM)"]
#: The run folder's lock, made before Ray starts and removed when the command ends.
LOCK = ".amuled.lock"


def _processes() -> dict[int, tuple[int, str]]:
    """Every process in sight: pid -> (parent pid, command name)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            text = (entry / "stat").read_text()
        except OSError:
            continue
        comm = text[text.index("(") + 1 : text.rindex(")")]
        ppid = int(text[text.rindex(")") + 2 :].split()[1])
        found[int(entry.name)] = (ppid, comm)
    return found


def _has_child(pid: int, name: str) -> bool:
    return any(ppid == pid and comm.startswith(name) for ppid, comm in _processes().values())


def _state(pid: int) -> str:
    """A process's state letter (``Z``: exited, not yet reaped); ``"-"`` once it is gone."""
    try:
        text = (Path("/proc") / str(pid) / "stat").read_text()
    except OSError:
        return "-"
    return text[text.rindex(")") + 2]


def _reap() -> None:
    """Reap exited children (this script is PID 1 here: Ray's orphans are its children)."""
    with contextlib.suppress(ChildProcessError):
        while os.waitpid(-1, os.WNOHANG) != (0, 0):
            pass


def _live_others() -> list[int]:
    """Live processes in this namespace but this one (exited, unreaped ones are gone)."""
    me = os.getpid()
    return [pid for pid in _processes() if pid != me and _state(pid) not in ("Z", "-")]


def _end_leftovers(grace: float = 3.0) -> list[str]:
    """The names of Ray's processes that outlived the driver by ``grace`` s; SIGKILL those."""
    deadline = time.monotonic() + grace
    while (left := _live_others()) and time.monotonic() < deadline:
        _reap()
        time.sleep(0.05)
    names = sorted(_processes().get(pid, (0, "?"))[1] for pid in left)
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while _live_others() and time.monotonic() < deadline:
        _reap()
        time.sleep(0.05)
    _reap()
    return names


def _python_stacks(pid: int) -> str:
    """Every thread's Python stack of a hung driver, from py-spy when it is installed."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(spy).exists():
        return "(py-spy not installed: pip install py-spy for the stacks of a hung run)"
    done = subprocess.run([spy, "dump", "--pid", str(pid)], capture_output=True, text=True)
    return (done.stdout + done.stderr)[-6000:]


def one_run(work: Path, index: int, delay: float, wait: float) -> dict:
    """Start the run, SIGTERM it ``delay`` s after its ``gcs_server`` appears."""
    runs = work / f"runs-{index}"
    err_path = work / f"{index}.err"
    env = {**os.environ, "GIT_PYTHON_REFRESH": "quiet", "RAY_USAGE_STATS_ENABLED": "0"}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    args = [sys.executable, "-m", "amuled_ma", "run", "findmilk", "--jobs", "2",
            "--run-dir", str(runs / "x"), *TINY]  # fmt: skip
    with open(err_path, "w") as err:
        proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=err, cwd=REPO)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if _has_child(proc.pid, "gcs_server"):
            break
        time.sleep(0.005)
    if proc.poll() is not None:
        return {"run": index, "code": "early", "stderr": err_path.read_text()[-2000:]}
    time.sleep(delay)
    early = proc.poll() is not None  # ray.init finished and the run ended (not expected)
    # the driver writes its run folder (more than its lock) once Ray has started
    started = any(p.name != LOCK for p in runs.rglob("*") if p.is_file())
    os.kill(proc.pid, signal.SIGTERM)
    sent = time.monotonic()
    stack = ""
    try:
        code: int | str = proc.wait(timeout=wait)
    except subprocess.TimeoutExpired:
        code = "hang"
        stack = _python_stacks(proc.pid)
        proc.kill()
        proc.wait()
    seconds = round(time.monotonic() - sent, 2)
    if isinstance(code, int) and code < 0:
        code = 128 - code  # killed by signal -code, as a shell reports it
    stderr = err_path.read_text()
    lines = [line for line in stderr.splitlines() if line.strip() and not RAY_CORE_LOG.match(line)]
    left = any(p.name != LOCK for p in runs.rglob("*") if p.is_file())
    leftovers = _end_leftovers()
    return {
        "run": index,
        "delay": round(delay, 3),
        "code": code,
        "seconds": seconds,
        "one_line": lines == ONE_LINE,
        "folder_left": left,
        "ray_processes_left": leftovers,
        "early": early,
        "after_start": started,
        "stderr": "" if lines == ONE_LINE else stderr[-2000:],
        "stack": stack,
    }


def inside(count: int, spread: float, wait: float, work: Path) -> int:
    """The loop, run inside the namespaces."""
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    codes: collections.Counter[str] = collections.Counter()
    bad = during = 0
    for index in range(count):
        delay = spread * ((index * 0.6180339887) % 1.0)  # any first runs spread evenly
        result = one_run(work, index, delay, wait)
        # after Ray's start the run stops as on Ctrl-C (checkpoints, `resume with: ...`)
        clean = result.get("after_start") or (
            result.get("one_line") and not result.get("folder_left")
        )
        ok = result["code"] == 143 and clean
        bad += not ok
        during += not result.get("after_start")
        codes[str(result["code"])] += 1
        print(json.dumps(result), flush=True)
    summary = {"runs": count, "during_start": during, "exit_codes": dict(codes), "not_clean": bad}
    print("SUMMARY " + json.dumps(summary))
    return 0 if bad == 0 else 1


def main() -> int:
    """Run the loop inside fresh namespaces (or, with ``--inside``, here)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=100, help="runs (default 100)")
    parser.add_argument(
        "--spread", type=float, default=3.0, help="latest SIGTERM after gcs_server starts (s)"
    )
    parser.add_argument("--wait", type=float, default=60.0, help="seconds to exit (else hang)")
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: temp)")
    parser.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="sigterm-ray-"))
    work.mkdir(parents=True, exist_ok=True)
    if args.inside:
        return inside(args.count, args.spread, args.wait, work)
    again = [sys.executable, __file__, "--inside", "--count", str(args.count), "--spread",
             str(args.spread), "--wait", str(args.wait), "--work", str(work)]  # fmt: skip
    return subprocess.run([*OWN_NAMESPACES, *again], check=False).returncode


if __name__ == "__main__":
    sys.exit(main())
