"""Ray's import-time switches: a local Ray on loopback only, the driver's SIGTERM kept."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

#: Ray's switch between a one-machine Ray, whose processes listen on loopback only, and a
#: cluster node; Ray reads it once, when it is imported (`prefer_loopback`).
SINGLE_MACHINE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


#: Ray's switch for its C++ failure-signal handler, read once, when Ray is imported
#: (`keep_sigterm`).
FAILURE_HANDLER_ENV = "RAY_DISABLE_FAILURE_SIGNAL_HANDLER"


#: Ray's switch for how long a node started by this process drains on a SIGTERM before
#: it kills its processes (default 30 s), read once, when Ray is imported
#: (`keep_sigterm`).
DRAIN_ENV = "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S"


def _restore(name: str, before: str | None) -> None:
    """Put environment variable ``name`` back to ``before`` (None: unset)."""
    if before is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = before


def keep_sigterm() -> None:
    """Keep Ray's C++ core worker from taking this driver's SIGTERM while ``ray.init`` runs.

    Its handler would abort (exit 134, no checkpoint). Also sets Ray's drain time to 0 unless
    set (else a SIGTERM waits up to 30 s). Affects the import of Ray only; a no-op after.
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
    """Make the local Ray this process will start listen on loopback only (before Ray is imported).

    Not for ``--ray ADDRESS``: a cluster's nodes must reach the driver.
    """
    if "ray" not in sys.modules:
        os.environ[SINGLE_MACHINE_ENV] = "0"


@contextlib.contextmanager
def ray_switches(local: bool) -> Iterator[None]:
    """Ray's import-time switches for the ``with`` block, undone after."""
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
