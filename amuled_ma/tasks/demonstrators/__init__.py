"""The paper authors' synthetic human feedback: played demonstrators and their count beliefs.

docs/tasks.md, "The authors' synthetic human demonstrators".
"""

from __future__ import annotations

import os
from pathlib import Path

from amuled_ma.tasks import canonical_name
from amuled_ma.tasks.demonstrators.play import (
    driving_human_reward,
    findmilk_weights,
    play_driving,
    play_findmilk,
    sarsa_update,
)
from amuled_ma.tasks.demonstrators.table import (
    AUTHORS_STATE_COUNTS,
    DEFAULT_EPISODES,
    DRIVING_COUNT_FROM,
    DemonstratorBelief,
    DemonstratorCacheError,
    counts_to_belief,
    demonstrator_settings,
    encode_observations,
    settings_differences,
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


def cache_path(cache_dir: str | os.PathLike, task_name: str, *, seed: int, episodes: int) -> Path:
    """Return ``cache_dir/human_demonstrator_<task>_seed<seed>_episodes<episodes>.npz``."""
    name = canonical_name(task_name)
    return Path(cache_dir) / f"human_demonstrator_{name}_seed{seed}_episodes{episodes}.npz"


def demonstrator_belief(
    task_name: str,
    *,
    seed: int,
    episodes: int | None = None,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = False,
) -> DemonstratorBelief:
    """Build the authors' synthetic human belief table of a task, or load it from the cache.

    ``episodes`` None: the authors' (`DEFAULT_EPISODES`); ``cache_dir`` None keeps no file; a
    file made with other settings is rebuilt and overwritten.

    Raises:
        ValueError: An argument is out of range.
        DemonstratorCacheError: The cache file exists but cannot be read.
    """
    settings = demonstrator_settings(task_name, seed=seed, episodes=episodes)
    name, episodes = settings["task"], settings["episodes"]
    path = None
    if cache_dir is not None:
        path = cache_path(cache_dir, name, seed=settings["seed"], episodes=episodes)
        if path.exists():
            cached = DemonstratorBelief.load(path)
            if not settings_differences(cached.settings, settings) and cached.task_name == name:
                return cached
    play = play_findmilk if name == "findmilk" else play_driving
    belief = play(seed=settings["seed"], episodes=episodes, progress=progress)
    if path is not None:
        belief.save(path)
    return belief
