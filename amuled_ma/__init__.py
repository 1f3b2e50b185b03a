"""amuled-ma: ethical fine-tuning of RL agents with feedback from a panel of LLM moral clusters.

Importing the package registers the task environments with Gymnasium
(``amuled/FindMilk-v0``, ``amuled/Driving-v0``) once the task sub-package exists.
"""

from __future__ import annotations

__version__ = "0.1.0"


def _register_environments() -> None:
    """Register the Gymnasium ids of every task (idempotent)."""
    try:
        from amuled_ma.tasks import registration
    except ImportError:  # pragma: no cover - only while the tasks package is being built
        return
    registration.register_all()


_register_environments()
