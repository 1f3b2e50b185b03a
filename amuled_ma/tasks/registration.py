"""Register the Gymnasium ids of the tasks (called on ``import amuled_ma``).

Only strings here: registering imports neither torch nor the task modules.
"""

from __future__ import annotations

import gymnasium

__all__ = ["GYM_IDS", "register_all"]

GYM_IDS: dict[str, str] = {
    "amuled/FindMilk-v0": "amuled_ma.tasks.gym_env:FindMilkEnv",
    "amuled/Driving-v0": "amuled_ma.tasks.gym_env:DrivingEnv",
}


def register_all() -> None:
    """Register ``amuled/FindMilk-v0`` and ``amuled/Driving-v0`` (idempotent).

    The episode time limit is part of the environment (``max_steps``, default 300), so no
    ``TimeLimit`` wrapper is added.
    """
    for env_id, entry_point in GYM_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point)
