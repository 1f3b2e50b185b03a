"""SIGTERM to ``amuled run --ray HOST:PORT`` on a Ray cluster, and during ``ray.init``.

``sigterm_cluster_netns.py`` runs in network and PID namespaces this test makes
(``unshare -n -p -f --mount-proc``): loopback only, so Ray cannot pick an external
interface and no traffic leaves the machine; and a PID namespace, so that the
``ray stop --force`` that ends it stops this cluster alone, not another Ray of the machine.

- A running sweep on the cluster: SIGTERM checkpoints both running fine-tunes, prints one
  ``resume with:`` line and exits 143; that command, run as printed, finishes both to the
  planned iteration, keeping the iterations done before the stop.
- SIGTERM inside ``ray.init`` (before any job): exit 143, one line, no traceback, no run
  folder. Left to Ray, its handler for the time of ``ray.init`` runs ``sys.exit(15)``
  (exit 15, nothing said) or its C++ core worker aborts ("SIGTERM received", exit 134);
  on a local Ray its node's handler exits 1; and the run folder (``config.json``) stays.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
from netns import OWN_PIDS, require_netns, run_sealed

SCRIPT = Path(__file__).resolve().parent / "sigterm_cluster_netns.py"
ITERATIONS = 600  # the script's fine-tune length


#: A warning of Ray's C++ core, printed to the driver's stderr by Ray itself while it
#: looks up the node's address, before its logger reads any setting (in a network namespace
#: without a route out: "network_util.cc:330: Failed to determine local IP via external
#: connectivity"). It is Ray's line, not the command's: the command's own output is checked.
RAY_CORE_LOG = re.compile(r"^\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} [WI] \d+ \d+\] \w+\.cc:\d+: ")


def one_line(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip() and not RAY_CORE_LOG.match(line)]


@pytest.mark.slow
def test_sigterm_on_a_ray_cluster_checkpoints_and_the_printed_resume_finishes(tmp_path):
    require_netns(own_pids=True)
    result, _output = run_sealed(
        SCRIPT, ["stop", str(tmp_path)], timeout=1500, env=os.environ, own_pids=True
    )
    err = result["stderr"]
    assert result["code"] == 143, err
    assert "Traceback" not in err and "SIGTERM received" not in err, err
    assert "amuled: terminated (SIGTERM)" in err, err
    assert result["seconds"] < 60, result["seconds"]
    (hint,) = result["hints"]
    assert "--ray 127.0.0.1:" in hint and hint.endswith(" --resume"), hint
    for tune, state in result["stopped"].items():  # each running job wrote its checkpoint
        assert state is not None and not state["completed"], (tune, state)
        assert 100 <= state["iteration"] < ITERATIONS, (tune, state)
    assert result["resume_code"] == 0, result["resume_tail"]
    for tune, state in result["final"].items():
        assert state["completed"] and state["iteration"] == ITERATIONS, (tune, state)
    assert all(result["iterations"].values()), result["iterations"]
    assert all(result["kept_before_stop"].values()), result["kept_before_stop"]


@pytest.mark.slow
def test_sigterm_during_ray_init_is_one_line_and_leaves_no_run_folder(tmp_path):
    require_netns(own_pids=True)
    result, _output = run_sealed(
        SCRIPT, ["init", str(tmp_path)], timeout=900, env=os.environ, own_pids=True
    )
    for where in ("local", "cluster"):
        case = result[where]
        assert case["code"] == 143, (where, case)
        assert one_line(case["stderr"]) == ["amuled: terminated (SIGTERM)"], (where, case)
        assert case["left"] is None, (where, case["left"])  # no run folder, no parent made


def test_the_script_exists_and_the_pid_namespace_is_permitted():
    """A cheap check that runs without the slow marker: the launcher's namespaces work."""
    require_netns(own_pids=True)
    probe = subprocess.run(
        [*OWN_PIDS, "sh", "-c", "echo $$"],
        capture_output=True, text=True, timeout=30, env=dict(os.environ),
    )  # fmt: skip
    assert probe.returncode == 0 and probe.stdout.strip() == "1", probe
    assert SCRIPT.is_file()
