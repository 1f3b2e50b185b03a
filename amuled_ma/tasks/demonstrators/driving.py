"""The authors' Driving demonstrator (``algorithms/human_policy_drive.py``), batched.

A tabular SARSA-style Q-learner whose table is empty at every episode's start: unseen
``Q(s, .) ~ N(0, 1)``, policy ``p(a) ∝ exp(Q(s, a) / 0.7)``, reward `driving_human_reward`.
Episodes 601..9999 are counted (the authors' ``if cnt > 600``); the earlier ones cannot
change a count (fresh table, own streams), so they are not played.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

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
    DRIVING_COUNT_FROM,
    MAX_STEPS,
    DemonstratorBelief,
    encode_observations,
)
from amuled_ma.tasks.driving import Driving

__all__ = ["driving_human_reward", "play_driving", "sarsa_update"]

TEMPERATURE = 0.7
LEARNING_RATE = 0.1
DISCOUNT = 0.99
REWARD_RESCUE = 20.0
REWARD_COLLISION = -1.0
REWARD_STRAIGHT = 0.5

_DRAWS_PER_STEP = 5  # 4 for the normals of a new observation, 1 for the action
_TWO_PI = 2.0 * math.pi


def sarsa_update(
    q_prev: Any,
    reward: Any,
    q_next: Any = None,
    *,
    learning_rate: float = LEARNING_RATE,
    discount: float = DISCOUNT,
) -> Any:
    """Return the new ``Q(s, a)`` of the authors' SARSA step (``q_next`` None after the last)."""
    target = reward if q_next is None else reward + discount * q_next
    return q_prev + learning_rate * (target - q_prev)  # Q += lr (r + gamma Q(s', a') - Q)


def driving_human_reward(info: Mapping[str, torch.Tensor], actions: torch.Tensor) -> torch.Tensor:
    """Return the authors' ``ishuman_p`` reward float64 ``[num_envs]`` of one step."""
    return (
        REWARD_RESCUE * info["rescues"].to(torch.float64)
        + REWARD_COLLISION * info["collisions"].to(torch.float64)
        + REWARD_STRAIGHT * (actions == 0).to(torch.float64)
    )


def _play_wave(seed: int, first: int, n: int, max_steps: int, counter: PairCounter) -> None:
    """Play Driving episodes ``first..first+n-1`` side by side, one Q table each."""
    task = Driving(n, seed=task_seed(seed, first), max_steps=max_steps)
    obs = task.reset()
    streams = episode_streams(seed, first, n, task.device)
    rows = torch.arange(n)
    # The Q table of copy i: Q[i, slot] where slot = step of the episode on which the
    # observation was first met (at most one new observation per step); seen[i, t] holds
    # the key of step t and slot_of[i, t] its slot, so a key met again finds its slot.
    seen = torch.empty(n, max_steps, dtype=torch.int32)
    slot_of = torch.empty(n, max_steps, dtype=torch.int64)
    q = torch.empty(n, max_steps, 3, dtype=torch.float64)
    prev_slot = prev_action = prev_reward = None
    for t in range(max_steps):
        keys, _ = encode_observations("driving", obs)
        sid = keys.to(torch.int32)  # < 11**6 * 2**5 < 2**31
        if t:
            found, where = (seen[:, :t] == sid[:, None]).max(1)
            slot = torch.where(found, slot_of[rows, where], t)
        else:
            slot = torch.zeros(n, dtype=torch.int64)
        seen[:, t] = sid
        slot_of[:, t] = slot
        u = uniforms(streams, t * _DRAWS_PER_STEP, _DRAWS_PER_STEP)
        # standard normals (Box-Muller) for the Q row of a new observation; only read
        # where slot == t, i.e. the observation is new
        radius = torch.sqrt(-2.0 * torch.log1p(-u[:, 0:2]))
        angle = _TWO_PI * u[:, 2:4]
        normals = torch.cat([radius * torch.cos(angle), radius * torch.sin(angle)], 1)
        q[:, t] = normals[:, :3]
        q_s = q[rows, slot]  # [n, 3]
        actions = sample(torch.softmax(q_s / TEMPERATURE, 1), u[:, 4])
        if prev_slot is not None:
            q_next = q_s[rows, actions]
            q[rows, prev_slot, prev_action] = sarsa_update(
                q[rows, prev_slot, prev_action], prev_reward, q_next
            )
        counter.add(keys, actions)
        obs, _, _, _, info = task.step(actions)
        prev_slot, prev_action = slot, actions
        prev_reward = driving_human_reward(info, actions)
    # the last update, without bootstrap (the table is dropped after it, as the authors did)
    q[rows, prev_slot, prev_action] = sarsa_update(q[rows, prev_slot, prev_action], prev_reward)


def play_driving(
    *,
    seed: int,
    episodes: int = DEFAULT_EPISODES["driving"],
    count_from: int = DRIVING_COUNT_FROM,
    max_steps: int = MAX_STEPS,
    batch_size: int = 2500,
    progress: bool = False,
) -> DemonstratorBelief:
    """Play and count Driving episodes ``count_from..episodes-1``, ``batch_size`` side by side.

    Raises:
        ValueError: An argument is out of range.
    """
    return play_counted(
        "driving",
        _play_wave,
        seed=seed,
        episodes=episodes,
        count_from=count_from,
        max_steps=max_steps,
        batch_size=batch_size,
        progress=progress,
    )
