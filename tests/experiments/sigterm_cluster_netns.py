"""Run inside fresh network and PID namespaces: SIGTERM to ``amuled run`` on a Ray cluster.

``python sigterm_cluster_netns.py stop WORK`` or ``... init WORK``. Not a test itself:
``test_sigterm_ray_cluster.py`` runs it under ``unshare -n -p -f --mount-proc``
(``netns.run_sealed(..., own_pids=True)``: loopback only, and a PID namespace of its own,
so that ``ray stop --force`` at the end stops this cluster's processes and no other Ray of
the machine) and asserts on the ``RESULT {json}`` line it prints last. The cluster's
pieces are ``tests/ray_netns.py``.

``stop``: a head (``ray start --head --node-ip-address=127.0.0.1``, Ray's token
authentication, two CPUs); ``amuled run findmilk --ray 127.0.0.1:PORT`` on tiny settings;
once both fine-tunes have written a periodic checkpoint, SIGTERM to the driver alone
(``kill PID``); then the ``resume with:`` command it printed, run as printed.

``init``: SIGTERM while the driver is inside ``ray.init``, before any job starts: on a
local Ray (``--jobs 2``: once the driver has started the local Ray's ``gcs_server``) and
on the cluster (once the driver holds a connection to the head's port).
"""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: ray_netns
from ray_netns import cluster_env, main, start_node, stop_cluster

PORT = 6393
AMULED = [sys.executable, "-m", "amuled_ma"]
#: Fine-tune length: long enough that both still iterate when the first checkpoint is
#: written (every 100 iterations), short enough to resume to the end in the test.
ITERATIONS = 600
TINY = [
    "--episodes", "2", "--no-progress",
    "--set", "base.total_steps=1024", "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16", "--set", "finetune.num_envs=4",
    "--set", "finetune.num_steps_per_env=8", "--set", "output.tensorboard=false",
    "--set", 'feedback.source="rules"',
]  # fmt: skip
TUNES = ("finetune-human", "finetune-amuled")


def run_args(run_dir: Path, *where: str) -> list[str]:
    return [*AMULED, "run", "findmilk", "--run-dir", str(run_dir), *where, *TINY,
            "--set", f"finetune.iterations={ITERATIONS}"]  # fmt: skip


def start(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    """The command with stdout and stderr in files (``log``.out, .err)."""
    out = open(log.with_suffix(".out"), "w")  # noqa: SIM115 - closed with the process
    err = open(log.with_suffix(".err"), "w")  # noqa: SIM115
    return subprocess.Popen(args, env=env, stdout=out, stderr=err)


def sigterm(proc: subprocess.Popen, log: Path) -> dict:
    """SIGTERM to the driver alone; its exit status, stderr and seconds to exit."""
    sent = time.monotonic()
    os.kill(proc.pid, signal.SIGTERM)
    try:
        code = proc.wait(timeout=300)
    except subprocess.TimeoutExpired:
        stacks = _stacks(proc.pid)
        proc.kill()
        raise RuntimeError(f"no exit 300 s after SIGTERM; its threads:\n{stacks}") from None
    return {
        "code": code,
        "seconds": round(time.monotonic() - sent, 1),
        "stderr": log.with_suffix(".err").read_text(),
    }


def _stacks(pid: int) -> str:
    """Every thread's Python stack of a hung process (``py-spy dump``, when installed)."""
    spy = Path(sys.executable).with_name("py-spy")
    if not spy.exists():
        return "(py-spy not installed)"
    done = subprocess.run([str(spy), "dump", "--pid", str(pid)], capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    return done.stdout + done.stderr


def curve(folder: Path) -> list[dict]:
    rows = json.loads((folder / "curve.json").read_text())
    return [{k: v for k, v in r.items() if k != "wall_s" and not k.startswith("time/")}
            for r in rows]  # fmt: skip


def progress(path: Path) -> dict | None:
    """A checkpoint's iteration and whether it is complete (None: no checkpoint)."""
    from amuled_ma.learn.checkpoints import checkpoint_infos

    state = checkpoint_infos(path)
    if state is None:
        return None
    return {"iteration": int(state["iteration"]), "completed": bool(state.get("completed"))}


def stop_run(work: Path) -> dict:
    env = cluster_env()
    figures: dict = {}
    start_node(env, PORT, head=True, cpus=2)
    try:
        run_dir = work / "run"
        proc = start(run_args(run_dir, "--ray", f"127.0.0.1:{PORT}"), env, work / "stop")
        deadline = time.monotonic() + 400
        while time.monotonic() < deadline and proc.poll() is None:
            if all((run_dir / t / "model_last.pt").exists() for t in TUNES):
                break
            time.sleep(0.1)
        if proc.poll() is not None:
            raise RuntimeError("the run ended early:\n" + (work / "stop.err").read_text())
        time.sleep(1.0)
        figures.update(sigterm(proc, work / "stop"))
        stopped = {t: progress(run_dir / t / "model_last.pt") for t in TUNES}
        figures["stopped"] = stopped
        at_stop = {t: curve(run_dir / t) for t in TUNES if (run_dir / t / "curve.json").exists()}
        hints = [line[len("resume with: "):] for line in figures["stderr"].splitlines()
                 if line.startswith("resume with: ")]  # fmt: skip
        figures["hints"] = hints
        if len(hints) == 1:
            words = shlex.split(hints[0])
            assert words[0] == "amuled", words
            done = subprocess.run([*AMULED, *words[1:]], env=env, capture_output=True,
                                  text=True, timeout=900)  # fmt: skip
            figures["resume_code"] = done.returncode
            figures["resume_tail"] = done.stderr[-3000:]
            final = {t: progress(run_dir / t / "model_last.pt") for t in TUNES}
            figures["final"] = final
            figures["iterations"] = {t: [r["iteration"] for r in curve(run_dir / t)]
                                     == list(range(1, ITERATIONS + 1)) for t in TUNES}  # fmt: skip
            # the rows finished before the stop are kept, not trained again
            figures["kept_before_stop"] = {
                t: curve(run_dir / t)[: len(rows)] == rows for t, rows in at_stop.items()
            }
    finally:
        stop_cluster(env)
    return figures


def _children_named(pid: int, name: str) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1 : stat.rindex(")")]
        ppid = int(stat[stat.rindex(")") + 2 :].split()[1])
        if ppid == pid and comm.startswith(name):
            found.append(int(entry.name))
    return found


def _connected(pid: int, port: int) -> bool:
    """Whether process ``pid`` holds an established TCP connection to 127.0.0.1:``port``."""
    inodes = set()
    try:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            target = os.readlink(fd)
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    except OSError:
        return False
    for table in ("tcp", "tcp6"):  # gRPC connects over IPv6 sockets (v4-mapped addresses)
        try:
            lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        except OSError:  # the process is gone
            return False
        for line in lines:
            fields = line.split()
            remote_port = int(fields[2].split(":")[1], 16)
            if remote_port == port and fields[3] == "01" and fields[9] in inodes:
                return True
    return False


def init_case(work: Path, name: str, where: list[str], env: dict, inside) -> dict:
    """Start the run, SIGTERM it once ``inside(pid)`` says it is in ``ray.init``."""
    runs = work / f"runs-{name}"
    proc = start(run_args(runs / "x", *where), env, work / f"init-{name}")
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None and not inside(proc.pid):
        time.sleep(0.01)
    if proc.poll() is not None:
        raise RuntimeError(f"{name}: ended early:\n" + (work / f"init-{name}.err").read_text())
    figures = sigterm(proc, work / f"init-{name}")
    figures["left"] = sorted(str(p.relative_to(work)) for p in runs.rglob("*")) if (
        runs.exists()) else None  # fmt: skip
    return figures


def init_run(work: Path) -> dict:
    env = cluster_env()
    figures = {
        "local": init_case(work, "local", ["--jobs", "2"], env,
                           lambda pid: bool(_children_named(pid, "gcs_server"))),
    }  # fmt: skip
    start_node(env, PORT, head=True, cpus=2)
    try:
        figures["cluster"] = init_case(work, "cluster", ["--ray", f"127.0.0.1:{PORT}"], env,
                                       lambda pid: _connected(pid, PORT))  # fmt: skip
    finally:
        stop_cluster(env)
    return figures


if __name__ == "__main__":
    sys.exit(main({"stop": stop_run, "init": init_run}))
