"""The paper authors' synthetic human feedback: played demonstrators and their count beliefs.

One module per job: `.findmilk` and `.driving` (the demonstrators), `.play` (what both
share), `.table` (counts to beliefs, the ``.npz`` file), `.cache` (`demonstrator_belief`);
docs/tasks.md, "The authors' synthetic human demonstrators".
"""

from __future__ import annotations

from amuled_ma.tasks.demonstrators.cache import cache_path, demonstrator_belief
from amuled_ma.tasks.demonstrators.driving import (
    driving_human_reward,
    play_driving,
    sarsa_update,
)
from amuled_ma.tasks.demonstrators.findmilk import findmilk_weights, play_findmilk
from amuled_ma.tasks.demonstrators.table import (
    AUTHORS_STATE_COUNTS,
    DEFAULT_EPISODES,
    DRIVING_COUNT_FROM,
    DemonstratorBelief,
    DemonstratorCacheError,
    counts_to_belief,
    demonstrator_settings,
    encode_observations,
)

__all__ = [
    "AUTHORS_STATE_COUNTS",
    "DEFAULT_EPISODES",
    "DRIVING_COUNT_FROM",
    "DemonstratorBelief",
    "DemonstratorCacheError",
    "cache_path",
    "counts_to_belief",
    "demonstrator_belief",
    "demonstrator_settings",
    "driving_human_reward",
    "encode_observations",
    "findmilk_weights",
    "play_driving",
    "play_findmilk",
    "sarsa_update",
]
