"""amuled-ma: ethical fine-tuning of RL agents with feedback from a panel of LLM moral clusters.

Importing the package registers the task environments with Gymnasium,
``amuled/FindMilk-v0`` and ``amuled/Driving-v0``: ``gymnasium.make`` builds them from their
``module:Class`` entry points, so registering imports neither torch nor the task modules.
The episode time limit is the environment's own (``max_steps``, default 300), so no
``TimeLimit`` wrapper is added.
"""

from __future__ import annotations

import gymnasium

__version__ = "0.1.0"

gymnasium.register(id="amuled/FindMilk-v0", entry_point="amuled_ma.tasks.gym_env:FindMilkEnv")
gymnasium.register(id="amuled/Driving-v0", entry_point="amuled_ma.tasks.gym_env:DrivingEnv")
