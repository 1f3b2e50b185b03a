"""A Ray cluster on loopback, for scripts that ``netns.run_sealed(..., own_pids=True)`` runs.

Such a script runs in fresh network and PID namespaces (``unshare -n -p -f --kill-child
--mount-proc``): loopback only, so no traffic leaves the machine and Ray cannot pick an
external interface; and a PID namespace of its own, so that :func:`stop_cluster`
(``ray stop --force``) sees this cluster's processes alone, not another Ray of the machine,
and whatever is left dies with the namespace when the script ends.

The script puts ``tests/`` on ``sys.path`` (it runs as ``python SCRIPT``) to import this
module, does its work in ``MODE(work) -> figures`` functions and ends with :func:`main`,
which prints the figures as the ``RESULT {json}`` line the test reads.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import uuid
from collections.abc import Callable, Mapping
from pathlib import Path

#: The ``ray`` command beside this interpreter.
RAY = str(Path(sys.executable).with_name("ray"))


def cluster_env() -> dict[str, str]:
    """This process's environment with one token for the cluster's nodes and the driver."""
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "GIT_PYTHON_REFRESH": "quiet"}
    # Ray's token authentication
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=uuid.uuid4().hex + uuid.uuid4().hex)
    return env


def start_node(
    env: Mapping[str, str],
    port: int,
    *,
    head: bool,
    cpus: int,
    resources: Mapping[str, float] | None = None,
    private: Path | None = None,
) -> None:
    """``ray start`` a head on 127.0.0.1:``port``, or a node that joins it.

    ``resources``: custom resources the node offers; ``private``: a folder the node does not
    see (its own mount namespace, an empty tmpfs over the folder).
    """
    if head:
        temp_dir = tempfile.mkdtemp(prefix="r", dir="/tmp")  # socket paths must stay short
        args = [RAY, "start", "--head", f"--port={port}", "--include-dashboard=false"]
        args += [f"--temp-dir={temp_dir}"]
    else:
        args = [RAY, "start", f"--address=127.0.0.1:{port}"]
    if private is not None:
        script = f'mount -t tmpfs tmpfs "{private}" && exec "$0" "$@"'
        args = ["unshare", "-m", "--propagation", "private", "sh", "-c", script, *args]
    args += ["--node-ip-address=127.0.0.1", f"--num-cpus={cpus}", "--disable-usage-stats"]
    if resources:
        args += [f"--resources={json.dumps(dict(resources))}"]
    for attempt in (1, 2):
        done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=180)
        if done.returncode == 0:
            return
        # Ray waits a fixed 30 s for a new raylet to register, which a loaded machine can
        # miss ("Failed to get node info"): a head is stopped and started once more (a
        # node is not: `ray stop` would stop the head beside it)
        if head and attempt == 1 and "Failed to get node info" in done.stdout + done.stderr:
            stop_cluster(env)
            continue
        raise RuntimeError(f"{args} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")


def stop_cluster(env: Mapping[str, str]) -> None:
    """``ray stop --force``: in this PID namespace it sees this cluster's processes only."""
    subprocess.run([RAY, "stop", "--force"], env=env, capture_output=True, timeout=180)


def main(modes: Mapping[str, Callable[[Path], dict]]) -> int:
    """``python SCRIPT MODE WORK``: run ``modes[MODE](WORK)``, print ``RESULT {json}``."""
    mode, work = sys.argv[1], Path(sys.argv[2])
    figures = modes[mode](work)
    print("RESULT " + json.dumps(figures), flush=True)
    return 0
