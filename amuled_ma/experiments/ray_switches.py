"""Ray's import-time switches: a local Ray on loopback only, the driver's SIGTERM kept."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

#: Ray's switch between a one-machine Ray, whose processes listen on loopback only, and a
#: cluster node; read once, when Ray is imported.
SINGLE_MACHINE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
#: Ray's switch for its C++ failure-signal handler, which would take this driver's SIGTERM
#: while ``ray.init`` runs (exit 134, no checkpoint); read once, when Ray is imported.
FAILURE_HANDLER_ENV = "RAY_DISABLE_FAILURE_SIGNAL_HANDLER"
#: Ray's switch for how long a node started by this process drains on a SIGTERM before it
#: kills its processes (default 30 s); read once, when Ray is imported.
DRAIN_ENV = "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S"


def _restore(name: str, before: str | None) -> None:
    """Put environment variable ``name`` back to ``before`` (None: unset)."""
    if before is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = before


@contextlib.contextmanager
def ray_switches(local: bool) -> Iterator[None]:
    """Import Ray for the ``with`` block with its switches set; a no-op once Ray is imported.

    Ray's failure handler is off and its drain time 0 (unless set) for the import only;
    ``local`` makes the local Ray this process starts listen on loopback only (never for
    ``--ray ADDRESS``: a cluster's nodes must reach the driver), undone after the block.
    """
    before = {
        name: os.environ.get(name) for name in (SINGLE_MACHINE_ENV, FAILURE_HANDLER_ENV, DRAIN_ENV)
    }
    if "ray" not in sys.modules:
        if local:
            os.environ[SINGLE_MACHINE_ENV] = "0"
        os.environ[FAILURE_HANDLER_ENV] = "1"
        os.environ.setdefault(DRAIN_ENV, "0")
        try:
            import ray  # noqa: F401 - read the switches now
        finally:
            _restore(FAILURE_HANDLER_ENV, before[FAILURE_HANDLER_ENV])
            _restore(DRAIN_ENV, before[DRAIN_ENV])
    try:
        yield
    finally:
        # the local Ray's processes took the switch with them; a process this one starts
        # later (a `ray start --address` joining a cluster, say) must not inherit it
        _restore(SINGLE_MACHINE_ENV, before[SINGLE_MACHINE_ENV])
