"""Run a test script inside a network namespace the test makes itself (loopback only).

Tests that start servers or a cluster (several Ollama servers, a Ray cluster) run their
work in a fresh namespace: ``unshare -n``, then ``ip link set lo up``. No traffic can
leave the machine, and Ray cannot pick an external interface. The script prints its
figures as one line ``RESULT {json}``; :func:`run_sealed` returns them with the output.

With ``own_pids=True`` the script also gets a PID namespace of its own (``unshare -n -p -f
--kill-child --mount-proc``, :data:`OWN_PIDS`): it is PID 1 there, ``ray stop --force`` or
``pgrep`` inside see the namespace's processes only, and every process it started dies
with it (or with the launcher, on a timeout).

Needs root (or ``CAP_SYS_ADMIN``) and ``ip``; without them a test skips with the reason,
except under ``CI=true``, where it fails: CI runs these tests.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import pytest
from ollama_server_fixture import in_ci

#: ``unshare`` for a new network namespace.
NETWORK = ["unshare", "-n"]
#: ``unshare`` for a new network namespace and a PID namespace of its own (with its /proc).
OWN_PIDS = ["unshare", "-n", "-p", "-f", "--kill-child", "--mount-proc"]
#: Inside the new namespace: bring loopback up, then run the command.
LOOPBACK_UP = ["sh", "-c", 'ip link set lo up && exec "$0" "$@"']


def unavailable(reason: str) -> None:
    """Skip with ``reason``; fail under ``CI=true``."""
    if in_ci():
        pytest.fail(f"{reason} (CI=true: this test must run)")
    pytest.skip(reason)


def require_netns(*, own_pids: bool = False) -> None:
    """Skip (or fail in CI) unless ``unshare -n`` and ``ip`` work here.

    ``own_pids``: the PID namespace of :func:`run_sealed`'s ``own_pids`` must work too.
    """
    missing = [tool for tool in ("unshare", "ip") if shutil.which(tool) is None]
    if missing:
        unavailable(f"{' and '.join(missing)} not found: the test needs a network namespace")
    unshare = OWN_PIDS if own_pids else NETWORK
    probe = subprocess.run(
        [*unshare, "sh", "-c", "ip link set lo up"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    if probe.returncode != 0:
        unavailable(
            f"'{' '.join(unshare)}' is not permitted here (it needs root or CAP_SYS_ADMIN): "
            f"{probe.stderr.strip() or probe.returncode}"
        )


def run_sealed(
    script: Path,
    args: Sequence[str],
    *,
    timeout: float,
    env: Mapping[str, str],
    own_pids: bool = False,
) -> tuple[dict, str]:
    """Run ``python script args`` in a new network namespace; return RESULT and output.

    ``own_pids``: in a PID namespace of its own too (:data:`OWN_PIDS`). On a timeout the
    script gets SIGTERM (it cleans up its servers), then SIGKILL, and the test fails with
    the output's tail; with ``own_pids``, SIGKILL at once (``unshare`` ignores SIGTERM, and
    ``--kill-child`` takes every process of the namespace with it).
    """
    unshare = OWN_PIDS if own_pids else NETWORK
    command = [*unshare, *LOOPBACK_UP, sys.executable, str(script), *args]
    job = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=dict(env)
    )
    try:
        output, _ = job.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        if own_pids:  # unshare ignores SIGTERM; --kill-child takes the namespace with it
            job.kill()
        else:  # the script cleans up its servers
            job.send_signal(signal.SIGTERM)
        try:
            output, _ = job.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            job.kill()
            output, _ = job.communicate()
        pytest.fail(f"the sealed run took more than {timeout} s:\n{output[-6000:]}")
    lines = [line for line in output.splitlines() if line.startswith("RESULT ")]
    assert job.returncode == 0 and lines, f"exit {job.returncode}:\n{output[-6000:]}"
    return json.loads(lines[-1][len("RESULT ") :]), output
