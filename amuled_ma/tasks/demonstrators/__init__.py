"""The paper authors' synthetic human feedback: played demonstrators and their count beliefs.

## Description

The AMULED authors did not ask people for feedback. They played a *demonstrator* (in the
style of Wu and Lin, 2018) for many episodes, counted every ``(observation, action)`` pair it
produced, and turned the counts of each observation into a belief over actions. This package
does the same on our batched tasks (many episodes side by side as task copies), seeded, one
module per job:

- `.findmilk`: the FindMilk rule demonstrator (``algorithms/human_policy_milk.py``),
  1,000 episodes, every step counted;
- `.driving`: the Driving SARSA-style Q-learner (``algorithms/human_policy_drive.py``),
  10,000 episodes of 300 steps, counted from episode 601;
- `.play`: what both share: per-episode random streams (`rng`),
  the action draw, the pair counter;
- `.table`: observation keys, the counts-to-belief rule (``p(a) ∝ 0.6**c_a *
  0.4**(n - c_a)``, counts rescaled to total 20), the belief table and its ``.npz`` file;
- `.cache`: `demonstrator_belief`, built once and kept in a cache file.

## Usage

::

    from amuled_ma.tasks.demonstrators import demonstrator_belief
    table = demonstrator_belief("driving", seed=0, cache_dir=run_dir)
    beliefs, seen = table.lookup(obs)  # float32 [N, 3], bool [N]
    reward = torch.where(seen, beliefs.gather(1, actions[:, None])[:, 0], 0.0)

The demonstrators play on the CPU (the tables are small); ``lookup`` accepts observations
on any device and answers on that device.

## Version History

- v1: first version.
- v1.1: one module per job; the counts are unchanged.
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
