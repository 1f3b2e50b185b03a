"""The authors' FindMilk demonstrator (``algorithms/human_policy_milk.py``), batched.

A rule-driven sampled policy, action drawn with ``w / sum(w)`` (`findmilk_weights`); 1,000
episodes, each until the milk or the 300-step limit, every step counted.
"""

from __future__ import annotations

import torch

from amuled_ma.tasks.demonstrators.play import (
    PairCounter,
    episode_streams,
    play_counted,
    sample,
    task_seed,
    uniforms,
)
from amuled_ma.tasks.demonstrators.table import (
    DEFAULT_EPISODES,
    MAX_STEPS,
    DemonstratorBelief,
    encode_observations,
)
from amuled_ma.tasks.findmilk import SIZE, SLEEPING, FindMilk

__all__ = ["findmilk_weights", "play_findmilk"]

_MAX_DISTANCE = 24.0
_SLEEPING_WEIGHT = 1.0
_MILK_WEIGHT = 20.0
_FAR_WEIGHT = 5.0
_MOVES = ((0, 1), (0, -1), (-1, 0), (1, 0))  # up, down, left, right


def findmilk_weights(obs: torch.Tensor) -> torch.Tensor:
    """Return the FindMilk demonstrator's unnormalised weights float64 ``[N, 4]`` of the actions.

    Per action the next cell (clipped to the grid) weighs 1 on one of the six original
    sleeping-baby cells, else 20 on the milk, else ``(24 - d) / 24 * 20`` (``d``: Manhattan
    distance to the observed crying baby, ``(0, 0)`` when none is left), else 5.
    """
    obs = obs.to(torch.float64)
    moves = torch.tensor(_MOVES, dtype=torch.float64, device=obs.device)
    nxt = (obs[:, None, 0:2] + moves).clamp(0.0, SIZE - 1.0)  # [N, 4, 2]
    sleeping = torch.tensor(SLEEPING, dtype=torch.float64, device=obs.device)  # [6, 2]
    on_sleep = (nxt[:, :, None, :] == sleeping).all(-1).any(-1)
    on_milk = (nxt == obs[:, None, 2:4]).all(-1)
    d = (nxt - obs[:, None, 4:6]).abs().sum(-1)
    toward = torch.where(d < _MAX_DISTANCE, (_MAX_DISTANCE - d) / _MAX_DISTANCE * 20.0, _FAR_WEIGHT)
    return torch.where(on_sleep, _SLEEPING_WEIGHT, torch.where(on_milk, _MILK_WEIGHT, toward))


def _play_wave(seed: int, first: int, n: int, max_steps: int, counter: PairCounter) -> None:
    """Play FindMilk episodes ``first..first+n-1`` side by side, each until it ends."""
    task = FindMilk(n, seed=task_seed(seed, first), max_steps=max_steps)
    obs = task.reset()
    streams = episode_streams(seed, first, n, task.device)
    active = torch.ones(n, dtype=torch.bool)
    for t in range(max_steps):
        u = uniforms(streams, t, 1)[:, 0]
        actions = sample(findmilk_weights(obs), u)
        keys, _ = encode_observations("findmilk", obs)
        counter.add(keys[active], actions[active])
        obs, _, terminated, truncated, _ = task.step(actions)
        active &= ~(terminated | truncated)
        if not bool(active.any()):
            break


def play_findmilk(
    *,
    seed: int,
    episodes: int = DEFAULT_EPISODES["findmilk"],
    max_steps: int = MAX_STEPS,
    batch_size: int = 1000,
    progress: bool = False,
) -> DemonstratorBelief:
    """Play the FindMilk rule demonstrator, ``batch_size`` episodes side by side; count each step.

    Raises:
        ValueError: An argument is out of range.
    """
    return play_counted(
        "findmilk",
        _play_wave,
        seed=seed,
        episodes=episodes,
        count_from=0,
        max_steps=max_steps,
        batch_size=batch_size,
        progress=progress,
    )
