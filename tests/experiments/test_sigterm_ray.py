"""SIGTERM to the driver of a real ``amuled run --jobs 2`` on a local Ray; Ray's ports.

Each run is the command line in a network namespace the test makes (``unshare -n``): the
first with loopback only, the second with a second interface and a default route (the
address Ray would pick for itself), so a port bound to every interface shows.

What could go wrong without the driver's own handling: ``ray.init`` replaces the driver's
SIGTERM handler (its C++ core worker aborts: "SIGTERM received", exit 134, no checkpoint,
no resume command), and the local Ray's ports listen on every interface (``*`` and the
second interface's address).
"""

from __future__ import annotations

import ipaddress
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from netns import require_netns
from tiny_cli import RULES, TINY

from amuled_ma.learn.checkpoints import checkpoint_infos

AMULED = [sys.executable, "-m", "amuled_ma"]
ENV = {**os.environ, "GIT_PYTHON_REFRESH": "quiet"}
#: A namespace with loopback only.
LOOPBACK = 'ip link set lo up && exec "$0" "$@"'
#: A namespace with loopback and a second interface holding the default route (a dummy
#: interface where the kernel has the module, else one end of a veth pair).
TWO_INTERFACES = (
    "ip link set lo up && "
    "{ ip link add x0 type dummy 2>/dev/null || ip link add x0 type veth peer name x1; } && "
    "ip addr add 10.9.9.9/24 dev x0 && ip link set x0 up && "
    "{ ip link set x1 up 2>/dev/null || true; } && "
    'ip route add default via 10.9.9.1 dev x0 && exec "$0" "$@"'
)
VARIANTS = ("base", "shaped", "finetune-human", "finetune-amuled")
TUNES = ("finetune-human", "finetune-amuled")


def _run_args(run_dir: Path, iterations: int, jobs: int) -> list[str]:
    """``amuled run findmilk`` on the tiny settings, fine-tunes ``iterations`` long."""
    args = ["run", "findmilk", "--run-dir", str(run_dir), "--jobs", str(jobs)]
    return [*args, "--episodes", "2", *TINY, *RULES, "--set", f"finetune.iterations={iterations}"]


def _sealed(setup: str, args: list[str]) -> list[str]:
    return ["unshare", "-n", "sh", "-c", setup, *AMULED, *args]


def _start(setup: str, args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        _sealed(setup, args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=ENV,
    )


def _wait_for(paths: list[Path], proc: subprocess.Popen, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not all(p.exists() for p in paths):
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    assert all(p.exists() for p in paths), [p for p in paths if not p.exists()]


def _sigterm(proc: subprocess.Popen) -> tuple[str, float]:
    """SIGTERM to the driver alone (``kill PID``); returns stderr and seconds to exit."""
    started = time.monotonic()
    os.kill(proc.pid, signal.SIGTERM)
    _out, err = proc.communicate(timeout=180)
    return err, time.monotonic() - started


def _learned(row: dict) -> dict:
    """A curve row without its wall-clock figures."""
    return {k: v for k, v in row.items() if k != "wall_s" and not k.startswith("time/")}


def _weights(folder: Path) -> dict[str, list]:
    """The policy's and the value function's parameters in a variant's checkpoint."""
    import torch

    state = torch.load(folder / "model_last.pt", weights_only=True)
    return {
        f"{part}.{name}": tensor.flatten().tolist()
        for part in ("actor_state_dict", "critic_state_dict")
        for name, tensor in state[part].items()
    }


def _curve(folder: Path) -> list[dict]:
    return [_learned(row) for row in json.loads((folder / "curve.json").read_text())]


@pytest.mark.slow
def test_sigterm_to_a_ray_run_checkpoints_every_job_and_resumes_to_the_same_result(tmp_path):
    require_netns()
    run_dir = tmp_path / "run"
    proc = _start(LOOPBACK, _run_args(run_dir, 4000, jobs=2))
    # both fine-tunes iterate on Ray: each has written its first periodic checkpoint
    _wait_for([run_dir / t / "model_last.pt" for t in TUNES], proc)
    time.sleep(1.0)
    err, seconds = _sigterm(proc)
    assert proc.returncode == 143, err
    assert "SIGTERM received" not in err and "Traceback" not in err, err
    assert err.count("resume with: amuled run findmilk") == 1, err
    assert "amuled: terminated (SIGTERM)" in err
    assert seconds < 60, seconds
    stopped = {t: checkpoint_infos(run_dir / t / "model_last.pt") for t in TUNES}
    assert all(s is not None and not s["completed"] for s in stopped.values()), stopped
    assert all(100 <= s["iteration"] < 4000 for s in stopped.values()), stopped

    # resume (Ray again), to 3 iterations past the furthest stop
    target = max(s["iteration"] for s in stopped.values()) + 3
    resume = [*_run_args(run_dir, target, jobs=2), "--resume"]
    done = subprocess.run(_sealed(LOOPBACK, resume), capture_output=True, text=True, env=ENV)
    assert done.returncode == 0, done.stderr[-4000:]
    # the same run, never stopped (in this process's order, every job alone: bit-identical
    # to Ray's two workers, where each population of this one-seed run is one job)
    reference = tmp_path / "reference"
    alone = [*_run_args(reference, target, jobs=1), "--no-population"]
    once = subprocess.run([*AMULED, *alone], capture_output=True, text=True, env=ENV)
    assert once.returncode == 0, once.stderr[-4000:]
    for variant in ("base", "shaped"):  # finished before the SIGTERM: the same files
        assert _curve(run_dir / variant) == _curve(reference / variant), variant
        assert _weights(run_dir / variant) == _weights(reference / variant), variant
    for tune in TUNES:
        curve, expected = _curve(run_dir / tune), _curve(reference / tune)
        assert [row["iteration"] for row in curve] == list(range(1, target + 1)), tune
        assert checkpoint_infos(run_dir / tune / "model_last.pt")["completed"], tune
        # every iteration the stopped job had finished is the uninterrupted run's; the
        # SIGTERM lands inside an iteration, whose rollout the resume collects again
        # (docs/learning.md, exact resume), so the rows after it may differ
        k = stopped[tune]["iteration"]
        assert curve[:k] == expected[:k], tune


def _listening(pid: int) -> list[str]:
    """``ADDRESS:PORT`` of every TCP socket listening in ``pid``'s network namespace."""
    found = []
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] != "0A":  # TCP_LISTEN
                continue
            address, port = fields[1].split(":")
            words = [address[i : i + 8] for i in range(0, len(address), 8)]
            raw = b"".join(bytes.fromhex(word)[::-1] for word in words)  # host-order words
            found.append(f"{ipaddress.ip_address(raw)}:{int(port, 16)}")
    return found


def _loopback(endpoint: str) -> bool:
    address = ipaddress.ip_address(endpoint.rsplit(":", 1)[0])
    mapped = getattr(address, "ipv4_mapped", None)
    return address.is_loopback or (mapped is not None and mapped.is_loopback)


@pytest.mark.slow
def test_the_local_ray_listens_on_loopback_only_beside_another_interface(tmp_path):
    require_netns()
    run_dir = tmp_path / "run"
    proc = _start(TWO_INTERFACES, _run_args(run_dir, 4000, jobs=2))
    try:
        # the fine-tunes' tasks run: the GCS, the raylet, its agents, the actors, the workers
        _wait_for([run_dir / t / "config.json" for t in TUNES], proc)
        time.sleep(2.0)
        ports = _listening(proc.pid)
    finally:
        err, _seconds = _sigterm(proc)
    assert len(ports) >= 5, ports  # Ray's processes do listen (GCS, raylet x2, workers)
    assert [p for p in ports if not _loopback(p)] == [], ports
    assert proc.returncode == 143, err


LOST_ACTOR_SCRIPT = """
import json, sys, time
import ray
from amuled_ma.errors import AmuledError
from amuled_ma.experiments.ray_jobs import connect
from amuled_ma.experiments.ray_store import RemoteStore, start_store_actors
connect(None, 1)
(actor,) = start_store_actors([sys.argv[1] + "/beliefs.sqlite"]).values()
store = RemoteStore(actor)
before = store.lookup(["k"])
ray.kill(actor)  # as when its node's agent dies: the actor is gone for good
# ray.kill returns before the actor is gone: a call made at once may still be served;
# ask until the death is seen (bounded: 100 tries, 0.1 s apart)
error = None
for _ in range(100):
    try:
        store.lookup(["k"])
    except AmuledError as lost:
        error = str(lost)
        break
    time.sleep(0.1)
print("RESULT " + json.dumps({"before": before, "error": error}))
ray.shutdown()
"""


def test_a_lost_belief_store_actor_is_one_line_not_a_traceback(tmp_path):
    """Ray's ``ActorDiedError`` (several lines) is turned into one line naming the fix."""
    from netns import run_sealed

    require_netns()
    script = tmp_path / "lost_actor.py"
    script.write_text(LOST_ACTOR_SCRIPT)
    result, _output = run_sealed(script, [str(tmp_path)], timeout=300, env=ENV)
    assert result["before"] == {}
    error = result["error"]
    assert error is not None and "\n" not in error, error
    assert error.startswith("the sweep's belief store on the driver's node cannot be reached")
    # the kill may still be in flight under load: Ray then says the actor is unavailable
    assert "ActorDiedError" in error or "ActorUnavailableError" in error, error
    assert "--resume" in error, error
