"""Run a test script inside a network namespace the test makes itself (loopback only).

Tests that start servers or a cluster (several Ollama servers, a Ray cluster) run their
work in a fresh namespace: ``unshare -n``, then ``ip link set lo up``. No traffic can
leave the machine, and Ray cannot pick an external interface. The script prints its
figures as one line ``RESULT {json}``; :func:`run_sealed` returns them with the output.

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


def unavailable(reason: str) -> None:
    """Skip with ``reason``; fail under ``CI=true``."""
    if in_ci():
        pytest.fail(f"{reason} (CI=true: this test must run)")
    pytest.skip(reason)


def require_netns() -> None:
    """Skip (or fail in CI) unless ``unshare -n`` and ``ip`` work here."""
    missing = [tool for tool in ("unshare", "ip") if shutil.which(tool) is None]
    if missing:
        unavailable(f"{' and '.join(missing)} not found: the test needs a network namespace")
    probe = subprocess.run(
        ["unshare", "-n", "sh", "-c", "ip link set lo up"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    if probe.returncode != 0:
        unavailable(
            "'unshare -n' is not permitted here (it needs root or CAP_SYS_ADMIN): "
            f"{probe.stderr.strip() or probe.returncode}"
        )


def run_sealed(
    script: Path, args: Sequence[str], *, timeout: float, env: Mapping[str, str]
) -> tuple[dict, str]:
    """Run ``python script args`` in a new network namespace; return RESULT and output.

    On a timeout the script gets SIGTERM (it cleans up its servers), then SIGKILL, and the
    test fails with the output's tail.
    """
    command = [
        "unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$0" "$@"',
        sys.executable, str(script), *args,
    ]  # fmt: skip
    job = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=dict(env)
    )
    try:
        output, _ = job.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
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
