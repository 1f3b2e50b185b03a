"""SIGTERM while a local Ray starts leaves none of Ray's processes behind.

Ray's raylet starts its agents (``ray::DashboardAgent``, ``ray::RuntimeEnvAgent``) while
``ray.init`` runs; a SIGTERM then, ended by ``ray.shutdown``, left them running after the
driver had exited (over 60 s, seen with ``tools/sigterm_ray_start.py``). The run is a
real ``amuled run --jobs 2`` in a PID and network namespace of its own, where every
process in sight is the test's.
"""

from __future__ import annotations

import os

import pytest
from netns import require_netns, run_sealed
from tiny_cli import RULES, TINY

SCRIPT = """
import json, os, signal, subprocess, sys, time
from pathlib import Path

def processes():
    found = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                text = (entry / "stat").read_text()
            except OSError:
                continue
            state = text[text.rindex(")") + 2]
            if state != "Z":
                found[int(entry.name)] = text[text.index("(") + 1 : text.rindex(")")]
    return found

args = [sys.executable, "-m", "amuled_ma", "run", "findmilk", "--jobs", "2", *sys.argv[1:]]
driver = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
deadline = time.monotonic() + 240
while time.monotonic() < deadline and driver.poll() is None:
    if any(name.startswith("ray::Dashboa") for name in processes().values()):
        break
    time.sleep(0.005)
agents = sorted(n for n in processes().values() if n.startswith("ray::"))
driver.send_signal(signal.SIGTERM)
_, err = driver.communicate(timeout=120)
time.sleep(5.0)  # what Ray's shutdown ends is gone well within this
try:  # reap the exited ones (this script is PID 1 here: orphans are its children)
    while os.waitpid(-1, os.WNOHANG) != (0, 0):
        pass
except ChildProcessError:
    pass
left = sorted(n for p, n in processes().items() if p != os.getpid())
result = {"code": driver.returncode, "err": err, "agents": agents, "left": left}
print("RESULT " + json.dumps(result))
"""


@pytest.mark.slow
def test_no_ray_process_outlives_a_driver_stopped_while_ray_starts(tmp_path):
    require_netns(own_pids=True)
    script = tmp_path / "stop_while_starting.py"
    script.write_text(SCRIPT)
    run = ["--run-dir", str(tmp_path / "run"), "--episodes", "1", *TINY, *RULES]
    env = {**os.environ, "GIT_PYTHON_REFRESH": "quiet", "RAY_USAGE_STATS_ENABLED": "0"}
    result, output = run_sealed(script, run, timeout=300, env=env, own_pids=True)
    assert any(name.startswith("ray::Dashboa") for name in result["agents"]), output[-3000:]
    assert result["code"] == 143, result["err"]
    assert result["left"] == [], result
