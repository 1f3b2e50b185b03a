"""The authors' two demonstrators, batched, and what their play shares (their rules: docs/tasks.md).

Episode ``e`` of seed ``s`` plays the task seeded ``b_s + e`` and draws from the stream of
``c_s + e`` (``b_s``, ``c_s``: hashes of ``s``), so the counts do not depend on batching.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import torch

from amuled_ma.monitor.progress import Progress
from amuled_ma.tasks import get_task, rng
from amuled_ma.tasks.base import check_int
from amuled_ma.tasks.demonstrators.table import (
    DEFAULT_EPISODES,
    DRIVING_COUNT_FROM,
    MAX_STEPS,
    DemonstratorBelief,
    demonstrator_settings,
    encode_observations,
)
from amuled_ma.tasks.driving import Driving
from amuled_ma.tasks.findmilk import SIZE, SLEEPING, FindMilk

_TASK_STREAMS, _CHOICE_STREAMS = 0, 1  # purposes of the per-episode random streams


def _base_seed(seed: int, purpose: int) -> int:
    """Base of the per-episode seeds of ``seed`` for one purpose (0 task, 1 choices).

    A hash, so seeds ``s`` and ``s + 1`` share no stream (``seed + e`` would shift them by one).
    """
    return rng.splitmix64(rng.splitmix64(seed) ^ purpose) >> 2


def task_seed(seed: int, first: int) -> int:
    """Return the base seed of a task whose copy ``i`` plays episode ``first + i``."""
    return _base_seed(seed, _TASK_STREAMS) + first


def episode_streams(seed: int, first: int, count: int, device: torch.device) -> torch.Tensor:
    """Return the choice-stream keys int64 ``[count]`` of episodes ``first..first+count-1``."""
    return rng.copy_keys(_base_seed(seed, _CHOICE_STREAMS) + first, count, device)


def uniforms(keys: torch.Tensor, start: int, count: int) -> torch.Tensor:
    """Return draws ``start..start+count-1`` of each stream, float64 ``[N, count]`` in [0, 1)."""
    return rng.uniform53(rng.draws(keys, start, count))


def sample(weights: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Draw one action per row with probability ``weights / weights.sum()`` (inverse CDF)."""
    cdf = weights.cumsum(1)
    picked = (cdf <= (u * cdf[:, -1])[:, None]).sum(1)
    return picked.clamp_(max=weights.shape[1] - 1)


class PairCounter:
    """Accumulates ``(observation key, action)`` pairs, deduplicating now and then."""

    _COMPACT_AT = 4_000_000

    def __init__(self, num_actions: int) -> None:
        self.num_actions = num_actions
        self._raw: list[torch.Tensor] = []  # pair ids, one per counted step
        self._raw_size = 0
        self._unique: list[tuple[torch.Tensor, torch.Tensor]] = []  # (pair ids, counts)

    def add(self, keys: torch.Tensor, actions: torch.Tensor) -> None:
        """Count one pair per row: observation keys ``[N]`` and actions ``[N]``."""
        pairs = (keys * self.num_actions + actions).cpu()
        self._raw.append(pairs)
        self._raw_size += pairs.numel()
        if self._raw_size >= self._COMPACT_AT:
            self._compact()

    def _compact(self) -> None:
        if self._raw:
            self._unique.append(torch.unique(torch.cat(self._raw), return_counts=True))
            self._raw, self._raw_size = [], 0

    def result(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Return the sorted state keys ``[S]`` and their counts ``[S, num_actions]`` (int64)."""
        self._compact()
        if not self._unique:
            empty = torch.zeros(0, dtype=torch.int64)
            return empty, torch.zeros(0, self.num_actions, dtype=torch.int64)
        pairs = torch.cat([p for p, _ in self._unique])
        freq = torch.cat([f for _, f in self._unique])
        unique, inverse = torch.unique(pairs, return_inverse=True)
        total = torch.zeros(unique.numel(), dtype=torch.int64).index_add_(0, inverse, freq)
        states, rows = torch.unique(unique // self.num_actions, return_inverse=True)
        counts = torch.zeros(states.numel(), self.num_actions, dtype=torch.int64)
        counts[rows, unique % self.num_actions] = total
        return states, counts


#: Plays episodes ``first..first+n-1`` of one seed side by side, counting into the counter:
#: ``wave(seed, first, n, max_steps, counter)``.
Wave = Callable[[int, int, int, int, PairCounter], None]


def play_counted(
    task_name: str,
    wave: Wave,
    *,
    seed: int,
    episodes: int,
    count_from: int,
    max_steps: int,
    batch_size: int,
    progress: bool,
) -> DemonstratorBelief:
    """Play and count episodes ``count_from..episodes-1`` in waves of ``batch_size``.

    Raises:
        ValueError: An argument is out of range.
    """
    settings = demonstrator_settings(task_name, seed=seed, episodes=episodes)
    seed, episodes = settings["seed"], settings["episodes"]
    count_from = check_int(count_from, "count_from")
    if count_from >= episodes:
        raise ValueError(
            f"count_from: expected less than episodes ({episodes}) so something is counted, "
            f"got {count_from}"
        )
    settings["count_from"] = count_from
    settings["max_steps"] = max_steps = check_int(max_steps, "max_steps", 1)
    batch_size = check_int(batch_size, "batch_size", 1)
    counter = PairCounter(len(get_task(task_name).action_names))
    desc = f"{task_name} demonstrator"
    with Progress(desc, episodes - count_from, bar=progress, unit="episode") as bar:
        for first in range(count_from, episodes, batch_size):
            n = min(batch_size, episodes - first)
            wave(seed, first, n, max_steps, counter)
            bar.update(n)
    states, counts = counter.result()
    return DemonstratorBelief(task_name, states, counts, settings)


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


def _findmilk_wave(seed: int, first: int, n: int, max_steps: int, counter: PairCounter) -> None:
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
        _findmilk_wave,
        seed=seed,
        episodes=episodes,
        count_from=0,
        max_steps=max_steps,
        batch_size=batch_size,
        progress=progress,
    )


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


def _driving_wave(seed: int, first: int, n: int, max_steps: int, counter: PairCounter) -> None:
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
        _driving_wave,
        seed=seed,
        episodes=episodes,
        count_from=count_from,
        max_steps=max_steps,
        batch_size=batch_size,
        progress=progress,
    )
