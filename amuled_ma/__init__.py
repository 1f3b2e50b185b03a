"""amuled-ma: ethical fine-tuning of RL agents with feedback from a panel of LLM moral clusters.

Importing it registers ``amuled/FindMilk-v0`` and ``amuled/Driving-v0`` with Gymnasium by entry
point (no torch import); the episode limit is the environment's ``max_steps``, no ``TimeLimit``.
"""

from __future__ import annotations

import gymnasium

__version__ = "0.1.0"

gymnasium.register(id="amuled/FindMilk-v0", entry_point="amuled_ma.tasks.gym_env:FindMilkEnv")
gymnasium.register(id="amuled/Driving-v0", entry_point="amuled_ma.tasks.gym_env:DrivingEnv")
