"""Run inside fresh network and PID namespaces: a two-node Ray cluster on loopback.

``python ray_cluster_netns.py kill WORK`` (a node killed mid-run) or ``... store WORK``
(the second node does not see the driver's files: its jobs' folders travel through Ray
and it reaches the belief store through the driver's store actor).

Not a test itself: ``test_ray_cluster.py`` runs it under ``unshare -n -p -f --mount-proc``
(``netns.run_sealed(..., own_pids=True)``: loopback only, so no traffic can leave the
machine and Ray cannot pick an external interface; and a PID namespace of its own, so that
the ``ray stop --force`` at the end stops this cluster alone) and asserts on the
``RESULT {json}`` line it prints last. The cluster's pieces are ``tests/ray_netns.py``.

``kill``:

1. ``amuled ablate findmilk --what aggregation --jobs 1`` on a tiny budget, in this process:
   the reference.
2. A head (``ray start --head``) and a second node (``ray start --address``), both on
   127.0.0.1, each offering one unit of the custom resource ``amuled_job``.
3. The same ablation with ``--ray HEAD --ray-resource amuled_job`` (jobs land on both
   nodes); once two fine-tunes have written a periodic checkpoint, the second node's
   raylet gets ``kill -9``. The run must finish, the lost job resumed from its checkpoint.

``store``: the shipped scenario's replay feedback, every lookup counted as if live:

1. The same ablation with ``--jobs 2`` on one machine (local Ray, one SQLite store): the
   requests it sends are the reference.
2. The second node is started in its own mount namespace with an empty ``tmpfs`` over
   WORK: it sees neither the run folder nor the store file.
3. The ablation on the cluster; its requests sent, against the reference.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: ray_netns
from ray_netns import cluster_env, main, start_node, stop_cluster

ITERATIONS, SAVE_EVERY = 150, 25
TINY = {
    "base.total_steps": "1024",
    "base.num_envs": "16",
    "base.num_steps_per_env": "16",
    "finetune.iterations": str(ITERATIONS),
    "finetune.save_interval": str(SAVE_EVERY),
    "finetune.num_envs": "4",
    "finetune.num_steps_per_env": "8",
    "output.tensorboard": "false",
    "feedback.source": '"rules"',
}
PORT = 6391
#: What each node offers besides its one CPU: one job at a time (``--ray-resource``).
JOB_SLOT = {"amuled_job": 1}


def ablate(run_dir: Path, *extra: str, settings: dict | None = None) -> list[str]:
    args = [sys.executable, "-m", "amuled_ma", "ablate", "findmilk", "--what", "aggregation"]
    # every job alone: these runs check Ray's cluster mechanics bit for bit against one
    # machine (populations are checked on Ray in tests/learn/test_jobs.py)
    args += ["--run-dir", str(run_dir), "--episodes", "2", "--no-progress", "--no-population"]
    args += list(extra)
    for key, value in (TINY if settings is None else settings).items():
        args += ["--set", f"{key}={value}"]
    return args


def raylets() -> set[int]:
    out = subprocess.run(["pgrep", "-x", "raylet"], capture_output=True, text=True).stdout
    return {int(pid) for pid in out.split()}


def learned(run_dir: Path) -> dict:
    """Each fine-tune's curve without wall times (a folder without one: None)."""
    out: dict = {}
    for folder in sorted((run_dir / "ablate-aggregation").glob("finetune-*")):
        if not (folder / "curve.json").is_file():
            out[folder.name] = None
            continue
        rows = json.loads((folder / "curve.json").read_text())
        out[folder.name] = [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]
    return out


def asked(run_dir: Path) -> int:
    """Requests the fine-tunes sent past the belief store (their ``feedback.json``)."""
    total = 0
    for path in (run_dir / "ablate-aggregation").glob("finetune-*/feedback.json"):
        total += json.loads(path.read_text())["store"]["asked"]
    return total


def store_run(work: Path) -> dict:
    env = cluster_env()
    # the tiny base leaves the recorded states often: keep going on replay misses
    replay = {k: v for k, v in TINY.items() if k != "feedback.source"}
    replay["feedback.max_abstention"] = "1.0"
    figures: dict = {}
    t0 = time.monotonic()
    args = ablate(work / "reference", "--jobs", "2", settings=replay)
    subprocess.run(args, env=env, check=True, capture_output=True, timeout=600)
    figures["reference_s"] = round(time.monotonic() - t0, 1)
    try:
        start_node(env, PORT, head=True, cpus=1, resources=JOB_SLOT)
        start_node(env, PORT, head=False, private=work, cpus=1, resources=JOB_SLOT)
        t0 = time.monotonic()
        args = ablate(work / "ray", "--ray", f"127.0.0.1:{PORT}", "--ray-resource",
                      "amuled_job", settings=replay)  # fmt: skip
        done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=900)
        figures["ray_run_s"] = round(time.monotonic() - t0, 1)
        output = done.stdout + done.stderr
        served = re.findall(r"served the jobs on other nodes: ([\d,]+) keys looked up in "
                            r"([\d,]+) calls, ([\d,]+) rows written", output)  # fmt: skip
        figures.update(
            code=done.returncode,
            nodes=sorted(set(re.findall(r"starts on Ray node ([0-9a-f]{8})", output))),
            reference_asked=asked(work / "reference"),
            ray_asked=asked(work / "ray") if done.returncode == 0 else None,
            served=[[int(x.replace(",", "")) for x in row] for row in served],
            equal_to_one_machine=learned(work / "ray") == learned(work / "reference"),
            fine_tunes=len(learned(work / "ray")),
            tail=output[-3000:],
        )
    finally:
        stop_cluster(env)
    return figures


def kill_run(work: Path) -> dict:
    env = cluster_env()
    figures: dict = {}
    t0 = time.monotonic()
    subprocess.run(ablate(work / "reference", "--jobs", "1"), env=env, check=True,
                   capture_output=True, timeout=600)  # fmt: skip
    figures["reference_s"] = round(time.monotonic() - t0, 1)
    try:
        t0 = time.monotonic()
        start_node(env, PORT, head=True, cpus=1, resources=JOB_SLOT)
        head_raylets = raylets()
        start_node(env, PORT, head=False, cpus=1, resources=JOB_SLOT)
        second = raylets() - head_raylets
        assert len(second) == 1, (head_raylets, second)
        figures["cluster_start_s"] = round(time.monotonic() - t0, 1)
        run_dir = work / "ray"
        log = open(work / "ray.log", "w")  # noqa: SIM115 - read after the run
        t0 = time.monotonic()
        proc = subprocess.Popen(
            ablate(run_dir, "--ray", f"127.0.0.1:{PORT}", "--ray-resource", "amuled_job"),
            env=env, stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        tunes = run_dir / "ablate-aggregation"
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            started = [p for p in tunes.glob("finetune-*/model_last.pt")]
            if len(started) >= 2:
                break
            time.sleep(0.2)
        killed = second.pop()
        os.kill(killed, signal.SIGKILL)
        figures["killed_at_s"] = round(time.monotonic() - t0, 1)
        code = proc.wait(timeout=600)
        figures["ray_run_s"] = round(time.monotonic() - t0, 1)
        log.close()
        output = (work / "ray.log").read_text()
        resumed = [int(n) for n in re.findall(r"resuming from iteration (\d+)", output)]
        nodes = sorted(set(re.findall(r"starts on Ray node ([0-9a-f]{8})", output)))
        same = learned(run_dir) == learned(work / "reference")
        figures.update(
            code=code, resumed_from=resumed, nodes=nodes, equal_to_jobs_1=same,
            fine_tunes=len(learned(run_dir)), tail=output[-3000:],
        )  # fmt: skip
    finally:
        stop_cluster(env)
    return figures


if __name__ == "__main__":
    sys.exit(main({"kill": kill_run, "store": store_run}))
