"""Ray's import-time switches: a local Ray on loopback only, the driver's SIGTERM kept.

Ray reads both environment variables once, when it is imported; :func:`ray_switches` sets
them around the import (:mod:`amuled_ma.experiments.jobs` connects and runs the jobs,
:mod:`amuled_ma.experiments.ray_jobs` names the switch when it was too late).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

#: Ray's switch between a one-machine Ray, whose processes listen on loopback only, and a
#: cluster node; Ray reads it once, when it is imported (:func:`prefer_loopback`).
SINGLE_MACHINE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


#: Ray's switch for its C++ failure-signal handler, read once, when Ray is imported
#: (:func:`keep_sigterm`).
FAILURE_HANDLER_ENV = "RAY_DISABLE_FAILURE_SIGNAL_HANDLER"


#: Ray's switch for how long a node started by this process drains on a SIGTERM before
#: it kills its processes (default 30 s), read once, when Ray is imported
#: (:func:`keep_sigterm`).
DRAIN_ENV = "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S"


def _restore(name: str, before: str | None) -> None:
    """Put environment variable ``name`` back to ``before`` (None: unset)."""
    if before is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = before


def keep_sigterm() -> None:
    """Keep Ray's C++ core worker from taking this driver's SIGTERM while ``ray.init`` runs.

    ``ray.init`` creates the driver's core worker, whose failure-signal handler (installed
    unless Ray's ``RAY_DISABLE_FAILURE_SIGNAL_HANDLER`` was set when Ray was imported)
    prints "SIGTERM received" and aborts (exit 134, no checkpoint, no resume command) for
    a SIGTERM that arrives before ``ray.init`` returns and the command's own handler is put
    back. Sets the switch for the import of Ray only: Ray's processes (its workers) keep
    their handler, which prints a stack trace when they crash. A no-op once Ray is
    imported.

    Also sets Ray's drain time to 0 (unless set already): the SIGTERM handler of the local
    node ``ray.init`` starts would otherwise wait up to 30 s for the node to drain (for
    Ray Serve's proxies; this run has none) before it stops Ray's processes and the
    command exits.
    """
    if "ray" in sys.modules:
        return
    before = {name: os.environ.get(name) for name in (FAILURE_HANDLER_ENV, DRAIN_ENV)}
    os.environ[FAILURE_HANDLER_ENV] = "1"
    os.environ.setdefault(DRAIN_ENV, "0")
    try:
        import ray  # noqa: F401 - read the switches now
    finally:
        for name, value in before.items():
            _restore(name, value)


def prefer_loopback() -> None:
    """Make the local Ray this process will start listen on loopback only.

    Sets Ray's ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` (a one-machine Ray: its node address,
    and so every port its processes open, is 127.0.0.1) before Ray is imported, which is
    when Ray reads it. A no-op once Ray is imported; then the local Ray listens on every
    interface, its calls still checked against this run's token
    (:func:`amuled_ma.experiments.ray_jobs.connect` says so). Not for ``--ray ADDRESS``:
    a cluster's nodes must reach the driver.
    """
    if "ray" not in sys.modules:
        os.environ[SINGLE_MACHINE_ENV] = "0"


@contextlib.contextmanager
def ray_switches(local: bool) -> Iterator[None]:
    """Ray's import-time switches for the ``with`` block.

    :func:`keep_sigterm`, and for a local Ray (``local``) :func:`prefer_loopback`, undone
    after: a process started later (a ``ray start --address`` joining a cluster, say) must
    not inherit it.
    """
    before = os.environ.get(SINGLE_MACHINE_ENV)
    if local:
        prefer_loopback()
    keep_sigterm()
    try:
        yield
    finally:
        # the local Ray's processes took the switch with them; a process this one starts
        # later (a `ray start --address` joining a cluster, say) must not inherit it
        _restore(SINGLE_MACHINE_ENV, before)
