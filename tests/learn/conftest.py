import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from fake_task import grid_factory

from amuled_ma.scenario import scenario_from_dict


@pytest.fixture
def tiny_scenario():
    return scenario_from_dict(
        {
            "task": {"name": "grid"},
            "base": {"total_steps": 4 * 32 * 6, "num_envs": 4, "num_steps_per_env": 32},
            "finetune": {"iterations": 4, "num_envs": 2, "num_steps_per_env": 16},
            "output": {"tensorboard": False},
        }
    )


@pytest.fixture
def factory():
    return grid_factory
