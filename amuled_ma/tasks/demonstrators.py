"""The paper authors' synthetic human feedback: played demonstrators and their count beliefs.

## Description

The AMULED authors did not ask people for feedback. They played a *demonstrator* (in the
style of Wu and Lin, 2018) for many episodes, counted every ``(observation, action)`` pair it
produced, and turned the counts of each observation into a belief over actions. This module
does the same on our batched tasks (many episodes side by side as task copies), seeded:

- **FindMilk** (the authors' ``algorithms/human_policy_milk.py``): a rule-driven *sampled*
  policy. For each action take the next cell (a move into a wall keeps the cell); its weight
  is 1 if that cell is one of the six *original* sleeping-baby cells (woken or not), else 20
  if it is the milk, else ``(24 - d) / 24 * 20`` with ``d`` the Manhattan distance from the
  next cell to the crying baby of the observation (``(0, 0)`` once none is left, as the
  authors did), else 5 (``d >= 24``, impossible on 8x8). The action is drawn with
  probabilities ``w / sum(w)``. 1,000 episodes, each until the milk or the 300-step time
  limit; every step is counted.
- **Driving** (``algorithms/human_policy_drive.py``): a tabular SARSA-style Q-learner whose
  table is *empty at the start of every episode*. ``Q(s, a)`` of an unseen observation is
  drawn from a standard normal (the three actions of a new observation together); the policy
  is Boltzmann, ``p(a) ∝ exp(Q(s, a) / 0.7)``; after the next action ``a'`` is drawn in
  ``s'``, ``Q(s, a) += 0.1 * (r + 0.99 * Q(s', a') - Q(s, a))``, and after the last step
  ``Q(s, a) += 0.1 * (r - Q(s, a))``. The reward is the authors' "human-preference" one,
  ``r = 20 * rescues - collisions + 0.5 * [straight]``, computed from the task's per-step
  ``info`` (the task's own reward is not used). 10,000 episodes of 300 steps; pairs are
  counted from episode index 601 on (the authors' ``if cnt > 600``: episodes 601..9999).

Counts to belief (the authors' ``finetune_moral_human.py``): per observation, ``c_a`` the
count of action ``a`` and ``n = sum(c)``; if ``n > 20`` the counts are rescaled to total 20;
then ``p(a) ∝ 0.6**c_a * 0.4**(n - c_a)``, normalised (computed in log space; it equals
``softmax(c_a * ln 1.5)``). An observation the demonstrator never met has no belief: the
authors' fine-tuning gives reward 0 there.

Observations are keyed exactly: every entry must be an integer within the task's
observation bounds (``obs_low``/``obs_high``); the key is the mixed-radix number of the
entries. Anything else (a fraction, out of bounds, NaN) is reported unseen.

## Usage

::

    from amuled_ma.tasks.demonstrators import demonstrator_belief
    table = demonstrator_belief("driving", seed=0, cache_dir=run_dir)
    beliefs, seen = table.lookup(obs)  # float32 [N, 3], bool [N]
    reward = torch.where(seen, beliefs.gather(1, actions[:, None])[:, 0], 0.0)

The demonstrators play on the CPU (the tables are small); ``lookup`` accepts observations
on any device and answers on that device.

## Random numbers

Episode ``e`` of a demonstrator seeded ``s`` plays on the task copy seeded ``b_s + e`` and
draws its own choices from the counter-based stream (:mod:`amuled_ma.tasks._rng`) of seed
``c_s + e``, where ``b_s`` and ``c_s`` are two hashes of ``s`` (so the episodes of seeds ``s``
and ``s + 1`` share no stream). The counts therefore depend on ``seed`` and the episode
indices only, not on how many episodes are played side by side.

Because the Driving Q table is reset every episode and every episode has its own streams,
an episode that is not counted cannot change any count; the Driving demonstrator therefore
plays only the counted episodes 601..9999 (the authors played 0..600 too and threw them
away, which also only advanced their random generator).

## Cache

:meth:`DemonstratorBelief.save` writes the counts to an ``.npz`` file (no pickle: it loads
with ``allow_pickle=False``) with the settings (task, demonstrator, seed, episodes,
counting start, time limit, observation encoding, format version) as JSON.
:func:`demonstrator_belief` keeps one file per task, seed and episode count in
``cache_dir``; a file whose recorded settings differ from the requested ones is rebuilt and
overwritten; an unreadable file raises :class:`DemonstratorCacheError`.

## Version History

- v1: first version (issue 13, item 2).
"""

from __future__ import annotations

import functools
import json
import math
import numbers
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from amuled_ma.errors import AmuledError
from amuled_ma.tasks import _rng, canonical_name, get_task

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

FORMAT_VERSION = 1
DEFAULT_EPISODES: Mapping[str, int] = {"findmilk": 1000, "driving": 10_000}
"""Episodes the authors played per task."""
DRIVING_COUNT_FROM = 601
"""First counted Driving episode (the authors' ``if cnt > 600``)."""
AUTHORS_STATE_COUNTS: Mapping[str, int] = {"findmilk": 1120, "driving": 12_270}
"""Distinct observations of the authors' demonstrator pickles (their notebook's figures)."""
MAX_STEPS = 300

# counts -> belief (finetune_moral_human.py)
COUNT_CAP = 20.0
P_AGREE = 0.6

# FindMilk rule (human_policy_milk.py)
_FM_MAX_DISTANCE = 24.0
_FM_SLEEPING_WEIGHT = 1.0
_FM_MILK_WEIGHT = 20.0
_FM_FAR_WEIGHT = 5.0
_FM_MOVES = ((0, 1), (0, -1), (-1, 0), (1, 0))  # up, down, left, right

# Driving Q-learner (human_policy_drive.py)
TEMPERATURE = 0.7
LEARNING_RATE = 0.1
DISCOUNT = 0.99
REWARD_RESCUE = 20.0
REWARD_COLLISION = -1.0
REWARD_STRAIGHT = 0.5

_MASK64 = (1 << 64) - 1
_TASK_STREAMS, _CHOICE_STREAMS = 0, 1  # purposes of the per-episode random streams
_DRAWS_PER_STEP = 5  # Driving: 4 for the normals of a new observation, 1 for the action
_TWO_PI = 2.0 * math.pi


class DemonstratorCacheError(AmuledError, ValueError):
    """A demonstrator cache file is unreadable, malformed or made with other settings."""


# ---------------------------------------------------------------------- observation keys
def _encoding(task_name: str) -> list[list[int]]:
    """Per observation entry ``[low, high]`` (integers) of the task's bounds."""
    cls = get_task(task_name)
    return [
        [math.floor(lo), math.ceil(hi)] for lo, hi in zip(cls.obs_low, cls.obs_high, strict=True)
    ]


@functools.cache
def _encoder(task_name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """CPU tensors ``low``, ``high`` (float64) and the int64 place value of each entry."""
    bounds = _encoding(task_name)
    weight, place = [], 1
    for lo, hi in reversed(bounds):
        weight.append(place)
        place *= hi - lo + 1
    if place >= 1 << 62:
        raise ValueError(f"{task_name}: observation bounds too wide for int64 keys")
    return (
        torch.tensor([b[0] for b in bounds], dtype=torch.float64),
        torch.tensor([b[1] for b in bounds], dtype=torch.float64),
        torch.tensor(weight[::-1], dtype=torch.int64),
    )


def encode_observations(task_name: str, obs: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Return the exact integer key of each observation and whether it could be keyed.

    The key is the mixed-radix number of the entries, each shifted by its lower bound
    (``obs_low``) with radix ``obs_high - obs_low + 1``. It is unique for integer-valued
    observations within the bounds; any other row gets key ``-1`` and ``valid`` false.

    Args:
        task_name: ``"findmilk"`` or ``"driving"`` (or an alias).
        obs: Observations ``[N, obs_dim]`` (tensor, array or nested list).

    Returns:
        ``(keys, valid)``: int64 ``[N]`` and bool ``[N]``, on the device of ``obs``
        (CPU for non-tensors).

    Raises:
        ValueError: ``obs`` is not ``[N, obs_dim]``.

    """
    name = canonical_name(task_name)
    low, high, weight = _encoder(name)
    values = obs if isinstance(obs, torch.Tensor) else torch.as_tensor(np.asarray(obs))
    if values.ndim != 2 or values.shape[1] != low.numel():
        raise ValueError(
            f"obs: expected shape [N, {low.numel()}] for task {name!r}, got {tuple(values.shape)}"
        )
    if values.device != low.device:
        low, high, weight = low.to(values.device), high.to(values.device), weight.to(values.device)
    values = values.to(torch.float64)
    valid = ((values == values.round()) & (values >= low) & (values <= high)).all(1)
    digits = torch.where(valid[:, None], values - low, 0.0).to(torch.int64)
    keys = (digits * weight).sum(1)
    return torch.where(valid, keys, -1), valid


# ---------------------------------------------------------------------- counts -> belief
def counts_to_belief(counts: Any) -> torch.Tensor:
    """Turn per-state action counts into beliefs (the authors' ``0.6 / 0.4`` rule).

    With ``n = sum(c)``: if ``n > 20`` the counts are rescaled to total 20; then
    ``p(a) ∝ 0.6**c_a * 0.4**(n - c_a)``, normalised, computed in log space.

    Args:
        counts: Non-negative counts ``[..., num_actions]``.

    Returns:
        float64 beliefs of the same shape, each row summing to 1.

    """
    c = torch.as_tensor(counts).to(torch.float64)
    n = c.sum(-1, keepdim=True)
    c = torch.where(n > COUNT_CAP, c * COUNT_CAP / n, c)
    n = c.sum(-1, keepdim=True)
    log_p = c * math.log(P_AGREE) + (n - c) * math.log(1.0 - P_AGREE)
    return torch.softmax(log_p, -1)


# ---------------------------------------------------------------------- random streams
def _splitmix64(value: int) -> int:
    """SplitMix64 of a Python integer (modulo 2**64)."""
    z = (value + 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def _base_seed(seed: int, purpose: int) -> int:
    """Base of the per-episode seeds of ``seed`` for one purpose (0 task, 1 choices).

    Episode ``e`` uses ``base + e``. The base is a hash of ``seed``, so the episodes of seeds
    ``s`` and ``s + 1`` do not share streams (``seed + e`` would shift them by one).
    """
    return _splitmix64(_splitmix64(seed) ^ purpose) >> 2


def _task_seed(seed: int, first: int) -> int:
    """Seed of a task whose copy ``i`` plays episode ``first + i`` of a demonstrator."""
    return _base_seed(seed, _TASK_STREAMS) + first


def _episode_keys(seed: int, first: int, count: int, device: torch.device) -> torch.Tensor:
    """Keys of the choice streams of episodes ``first..first+count-1`` (int64 ``[count]``)."""
    return _rng.copy_keys(_base_seed(seed, _CHOICE_STREAMS) + first, count, device)


def _uniforms(keys: torch.Tensor, start: int, count: int) -> torch.Tensor:
    """Draws ``start..start+count-1`` of each stream as float64 in ``[0, 1)``, ``[N, count]``."""
    ctr = torch.arange(start, start + count, dtype=torch.int64, device=keys.device)
    z = _rng.mix64(keys[:, None] + ctr * _rng.GAMMA)
    return _rng._srl(z, 11).to(torch.float64) * 2.0**-53


def _sample(weights: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Draw one action per row with probability ``weights / weights.sum()`` (inverse CDF)."""
    cdf = weights.cumsum(1)
    picked = (cdf <= (u * cdf[:, -1])[:, None]).sum(1)
    return picked.clamp_(max=weights.shape[1] - 1)


def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
    return int(seed)


def _check_count(value: Any, label: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{label}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


class _Counter:
    """Accumulates ``(observation key, action)`` pairs, deduplicating now and then."""

    _COMPACT_AT = 4_000_000

    def __init__(self, num_actions: int) -> None:
        self.num_actions = num_actions
        self._raw: list[torch.Tensor] = []  # pair ids, one per counted step
        self._raw_size = 0
        self._unique: list[tuple[torch.Tensor, torch.Tensor]] = []  # (pair ids, counts)

    def add(self, keys: torch.Tensor, actions: torch.Tensor) -> None:
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
        """Sorted state keys ``[S]`` and counts ``[S, num_actions]`` (int64)."""
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


def _progress_bar(total: int, desc: str, enabled: bool) -> Any:
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="episode", disable=not enabled, leave=False)


# ---------------------------------------------------------------------- FindMilk
def findmilk_weights(obs: torch.Tensor) -> torch.Tensor:
    """Return the FindMilk demonstrator's unnormalised weights of the four actions.

    Per action (up, down, left, right) the next cell, clipped to the grid, weighs 1 if it is
    one of the six original sleeping-baby cells, else 20 if it is the milk, else
    ``(24 - d) / 24 * 20`` with ``d`` the Manhattan distance to the observed crying baby
    (``(0, 0)`` when none is left), else 5.

    Args:
        obs: FindMilk observations ``[N, 8]``.

    Returns:
        float64 ``[N, 4]``.

    """
    from amuled_ma.tasks.findmilk import SIZE, SLEEPING

    obs = obs.to(torch.float64)
    moves = torch.tensor(_FM_MOVES, dtype=torch.float64, device=obs.device)
    nxt = (obs[:, None, 0:2] + moves).clamp(0.0, SIZE - 1.0)  # [N, 4, 2]
    sleeping = torch.tensor(SLEEPING, dtype=torch.float64, device=obs.device)  # [6, 2]
    on_sleep = (nxt[:, :, None, :] == sleeping).all(-1).any(-1)
    on_milk = (nxt == obs[:, None, 2:4]).all(-1)
    d = (nxt - obs[:, None, 4:6]).abs().sum(-1)
    toward = torch.where(
        d < _FM_MAX_DISTANCE, (_FM_MAX_DISTANCE - d) / _FM_MAX_DISTANCE * 20.0, _FM_FAR_WEIGHT
    )
    return torch.where(on_sleep, _FM_SLEEPING_WEIGHT, torch.where(on_milk, _FM_MILK_WEIGHT, toward))


def play_findmilk(
    *,
    seed: int,
    episodes: int = DEFAULT_EPISODES["findmilk"],
    max_steps: int = MAX_STEPS,
    batch_size: int = 1000,
    progress: bool = False,
) -> DemonstratorBelief:
    """Play the FindMilk rule demonstrator and count every ``(observation, action)``.

    Args:
        seed: Non-negative seed (episode ``e`` has its own streams, see the module notes).
        episodes: Episodes to play (the authors: 1,000), each until the milk or the limit.
        max_steps: Time limit of an episode.
        batch_size: Episodes played side by side (does not change the result).
        progress: Show a progress bar.

    Returns:
        The counts and beliefs.

    Raises:
        ValueError: An argument is out of range.

    """
    from amuled_ma.tasks.findmilk import FindMilk

    seed = _check_seed(seed)
    episodes = _check_count(episodes, "episodes", 1)
    max_steps = _check_count(max_steps, "max_steps", 1)
    batch_size = _check_count(batch_size, "batch_size", 1)
    counter = _Counter(len(FindMilk.action_names))
    with _progress_bar(episodes, "findmilk demonstrator", progress) as bar:
        for first in range(0, episodes, batch_size):
            n = min(batch_size, episodes - first)
            task = FindMilk(n, seed=_task_seed(seed, first), max_steps=max_steps)
            obs = task.reset()
            streams = _episode_keys(seed, first, n, task.device)
            active = torch.ones(n, dtype=torch.bool)
            for t in range(max_steps):
                u = _uniforms(streams, t, 1)[:, 0]
                actions = _sample(findmilk_weights(obs), u)
                keys, _ = encode_observations("findmilk", obs)
                counter.add(keys[active], actions[active])
                obs, _, terminated, truncated, _ = task.step(actions)
                active &= ~(terminated | truncated)
                if not bool(active.any()):
                    break
            bar.update(n)
    states, counts = counter.result()
    settings = demonstrator_settings("findmilk", seed=seed, episodes=episodes)
    settings["max_steps"] = max_steps
    return DemonstratorBelief("findmilk", states, counts, settings)


# ---------------------------------------------------------------------- Driving
def sarsa_update(
    q_prev: Any,
    reward: Any,
    q_next: Any = None,
    *,
    learning_rate: float = LEARNING_RATE,
    discount: float = DISCOUNT,
) -> Any:
    """Return the updated ``Q(s, a)`` of the authors' SARSA-style step.

    ``Q(s, a) + lr * (r + discount * Q(s', a') - Q(s, a))``, or without the bootstrap term
    after the last step (``q_next=None``): ``Q(s, a) + lr * (r - Q(s, a))``.

    Args:
        q_prev: ``Q(s, a)`` (number or tensor).
        reward: The reward ``r`` of that step.
        q_next: ``Q(s', a')`` of the next state and the action drawn there; ``None`` after
            the episode's last step.
        learning_rate: Step size (the authors: 0.1).
        discount: Discount (the authors: 0.99).

    Returns:
        The new ``Q(s, a)`` (same kind as the inputs).

    """
    target = reward if q_next is None else reward + discount * q_next
    return q_prev + learning_rate * (target - q_prev)


def driving_human_reward(info: Mapping[str, torch.Tensor], actions: torch.Tensor) -> torch.Tensor:
    """Return the authors' human-preference Driving reward of one step.

    ``20 * rescues - collisions + 0.5 * [action == straight]`` (their ``ishuman_p``).

    Args:
        info: The ``info`` of :meth:`Driving.step` (``rescues``, ``collisions``).
        actions: The actions of that step.

    Returns:
        float64 ``[num_envs]``.

    """
    return (
        REWARD_RESCUE * info["rescues"].to(torch.float64)
        + REWARD_COLLISION * info["collisions"].to(torch.float64)
        + REWARD_STRAIGHT * (actions == 0).to(torch.float64)
    )


def _driving_wave(seed: int, first: int, n: int, max_steps: int, counter: _Counter) -> None:
    """Play Driving episodes ``first..first+n-1`` side by side, one Q table each."""
    from amuled_ma.tasks.driving import Driving

    task = Driving(n, seed=_task_seed(seed, first), max_steps=max_steps)
    obs = task.reset()
    streams = _episode_keys(seed, first, n, task.device)
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
        u = _uniforms(streams, t * _DRAWS_PER_STEP, _DRAWS_PER_STEP)
        # standard normals (Box-Muller) for the Q row of a new observation; only read
        # where slot == t, i.e. the observation is new
        radius = torch.sqrt(-2.0 * torch.log1p(-u[:, 0:2]))
        angle = _TWO_PI * u[:, 2:4]
        normals = torch.cat([radius * torch.cos(angle), radius * torch.sin(angle)], 1)
        q[:, t] = normals[:, :3]
        q_s = q[rows, slot]  # [n, 3]
        actions = _sample(torch.softmax(q_s / TEMPERATURE, 1), u[:, 4])
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
    """Play the Driving Q-learning demonstrator and count ``(observation, action)`` pairs.

    Episodes ``count_from..episodes-1`` are played (each with a fresh Q table and its own
    random streams) and counted; the earlier ones could not change a count and are skipped.

    Args:
        seed: Non-negative seed (episode ``e`` has its own streams, see the module notes).
        episodes: Episode indices run to ``episodes - 1`` (the authors: 10,000).
        count_from: First counted episode index (the authors: 601).
        max_steps: Steps per episode (the authors: 300; the road never ends early).
        batch_size: Episodes played side by side (does not change the result).
        progress: Show a progress bar.

    Returns:
        The counts and beliefs.

    Raises:
        ValueError: An argument is out of range.

    """
    from amuled_ma.tasks.driving import Driving

    seed = _check_seed(seed)
    episodes = _check_count(episodes, "episodes", 1)
    count_from = _check_count(count_from, "count_from", 0)
    if count_from >= episodes:
        raise ValueError(
            f"count_from: expected less than episodes ({episodes}) so something is counted, "
            f"got {count_from}"
        )
    max_steps = _check_count(max_steps, "max_steps", 1)
    batch_size = _check_count(batch_size, "batch_size", 1)
    counter = _Counter(len(Driving.action_names))
    with _progress_bar(episodes - count_from, "driving demonstrator", progress) as bar:
        for first in range(count_from, episodes, batch_size):
            n = min(batch_size, episodes - first)
            _driving_wave(seed, first, n, max_steps, counter)
            bar.update(n)
    states, counts = counter.result()
    settings = demonstrator_settings("driving", seed=seed, episodes=episodes)
    settings["count_from"] = count_from
    settings["max_steps"] = max_steps
    return DemonstratorBelief("driving", states, counts, settings)


# ---------------------------------------------------------------------- belief table
def demonstrator_settings(task_name: str, *, seed: int, episodes: int | None = None) -> dict:
    """Return the settings a demonstrator belief of the authors' recipe is built with.

    Args:
        task_name: ``"findmilk"`` or ``"driving"`` (or an alias).
        seed: The demonstrator's seed.
        episodes: Episodes played (``None``: the authors' 1,000 / 10,000).

    Returns:
        A JSON-ready dict: ``format``, ``task``, ``demonstrator`` (``"rules"`` or
        ``"sarsa"``), ``seed``, ``episodes``, ``count_from``, ``max_steps``, ``encoding``.

    """
    name = canonical_name(task_name)
    seed = _check_seed(seed)
    episodes = DEFAULT_EPISODES[name] if episodes is None else episodes
    episodes = _check_count(episodes, "episodes", 1)
    return {
        "format": FORMAT_VERSION,
        "task": name,
        "demonstrator": "rules" if name == "findmilk" else "sarsa",
        "seed": seed,
        "episodes": episodes,
        "count_from": 0 if name == "findmilk" else DRIVING_COUNT_FROM,
        "max_steps": MAX_STEPS,
        "encoding": _encoding(name),
    }


class DemonstratorBelief:
    """Counts of a played demonstrator and the beliefs they give, keyed by observation.

    Args:
        task_name: ``"findmilk"`` or ``"driving"``.
        states: Observation keys (:func:`encode_observations`), int64 ``[S]``, strictly
            increasing.
        counts: Action counts per state, int64 ``[S, num_actions]``, every row summing to
            at least 1.
        settings: How the counts were made (:func:`demonstrator_settings`).

    Attributes:
        task_name: The task's short name.
        states: The sorted observation keys.
        counts: The counts.
        beliefs: float64 ``[S, num_actions]`` (:func:`counts_to_belief`).
        settings: The settings.

    Raises:
        ValueError: The arrays are malformed; the message says which.

    """

    def __init__(
        self,
        task_name: str,
        states: torch.Tensor,
        counts: torch.Tensor,
        settings: Mapping[str, Any],
    ) -> None:
        self.task_name = canonical_name(task_name)
        num_actions = len(get_task(self.task_name).action_names)
        states = torch.as_tensor(states).to(device="cpu", dtype=torch.int64).reshape(-1)
        counts = torch.as_tensor(counts).to(device="cpu", dtype=torch.int64)
        if counts.shape != (states.numel(), num_actions):
            raise ValueError(
                f"counts: expected shape ({states.numel()}, {num_actions}) for "
                f"{states.numel()} states of {self.task_name!r}, got {tuple(counts.shape)}"
            )
        if states.numel() > 1 and not bool((states[1:] > states[:-1]).all()):
            raise ValueError("states: expected strictly increasing observation keys")
        if bool((states < 0).any()) or bool((counts < 0).any()):
            raise ValueError("states/counts: expected non-negative values")
        if bool((counts.sum(1) < 1).any()):
            raise ValueError("counts: every state needs at least one counted action")
        self.states = states
        self.counts = counts
        self.beliefs = counts_to_belief(counts)
        self.settings = dict(settings)

    @property
    def num_states(self) -> int:
        """Number of distinct observations the demonstrator met."""
        return int(self.states.numel())

    @property
    def num_actions(self) -> int:
        """Number of actions of the task."""
        return int(self.counts.shape[1])

    def lookup(self, obs: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Return the belief of each observation and whether the demonstrator met it.

        Args:
            obs: Observations ``[N, obs_dim]`` (tensor, array or list), matched exactly.

        Returns:
            ``(beliefs, seen)``: float32 ``[N, num_actions]`` (rows of unseen observations
            are all 0, not a distribution) and bool ``[N]``, on the device of ``obs``
            (CPU for non-tensors).

        Raises:
            ValueError: ``obs`` is not ``[N, obs_dim]``.

        """
        device = obs.device if isinstance(obs, torch.Tensor) else torch.device("cpu")
        keys, valid = encode_observations(self.task_name, obs)
        keys = keys.cpu()
        where = torch.searchsorted(self.states, keys).clamp_(max=max(self.num_states - 1, 0))
        if self.num_states:
            seen = valid.cpu() & (self.states[where] == keys)
            beliefs = torch.where(seen[:, None], self.beliefs[where], 0.0)
        else:
            seen = torch.zeros(keys.numel(), dtype=torch.bool)
            beliefs = torch.zeros(keys.numel(), self.num_actions, dtype=torch.float64)
        return beliefs.to(device=device, dtype=torch.float32), seen.to(device)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the counts and settings to ``path`` (``.npz``, no pickle), atomically.

        Args:
            path: The file to write (its folder is created).

        Returns:
            The path written.

        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez_compressed(
                    f,
                    states=self.states.numpy(),
                    counts=self.counts.numpy(),
                    task=np.array(self.task_name),
                    settings=np.array(json.dumps(self.settings, sort_keys=True)),
                )
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, expect: Mapping[str, Any] | None = None
    ) -> DemonstratorBelief:
        """Read a file written by :meth:`save`.

        Args:
            path: The ``.npz`` file.
            expect: Settings the file must have been made with (every key compared);
                ``None`` accepts any.

        Returns:
            The belief table.

        Raises:
            DemonstratorCacheError: The file cannot be read, is malformed, or was made with
                other settings than ``expect`` (the message names the file and the fix).

        """
        path = Path(path)
        fix = "delete it to rebuild the demonstrator"
        try:
            with np.load(path, allow_pickle=False) as data:
                states = data["states"]
                counts = data["counts"]
                task = str(data["task"])
                settings = json.loads(str(data["settings"]))
        except (OSError, ValueError, KeyError, json.JSONDecodeError) as err:
            raise DemonstratorCacheError(
                f"{path}: not a readable demonstrator cache ({err}); {fix}"
            ) from err
        if not isinstance(settings, dict):
            raise DemonstratorCacheError(f"{path}: settings are not a JSON object; {fix}")
        if expect is not None:
            differ = _differences(settings, expect)
            if differ:
                raise DemonstratorCacheError(
                    f"{path}: made with other settings ({differ}); {fix}, or ask for those"
                )
        try:
            return cls(task, torch.from_numpy(states), torch.from_numpy(counts), settings)
        except (ValueError, TypeError) as err:
            raise DemonstratorCacheError(
                f"{path}: malformed demonstrator cache ({err}); {fix}"
            ) from err


def _differences(found: Mapping[str, Any], expect: Mapping[str, Any]) -> str:
    """Describe the keys of ``expect`` whose value in ``found`` differs (empty: none)."""
    return ", ".join(
        f"{k}: file {found.get(k)!r}, wanted {v!r}" for k, v in expect.items() if found.get(k) != v
    )


def cache_path(cache_dir: str | os.PathLike, task_name: str, *, seed: int, episodes: int) -> Path:
    """Return the cache file of a demonstrator belief in ``cache_dir``.

    ``human_demonstrator_<task>_seed<seed>_episodes<episodes>.npz``.
    """
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
    """Build the authors' synthetic human belief of a task, or load it from the cache.

    Args:
        task_name: ``"findmilk"`` or ``"driving"`` (or an alias).
        seed: The demonstrator's seed.
        episodes: Episodes played (``None``: the authors' 1,000 / 10,000). Driving counts
            from episode 601, so it needs more than 601.
        cache_dir: Folder of the cache file (:func:`cache_path`); ``None``: no cache. A file
            made with other settings is rebuilt and overwritten.
        progress: Show a progress bar while playing.

    Returns:
        The belief table.

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
            if not _differences(cached.settings, settings) and cached.task_name == name:
                return cached
    if name == "findmilk":
        belief = play_findmilk(seed=settings["seed"], episodes=episodes, progress=progress)
    else:
        belief = play_driving(seed=settings["seed"], episodes=episodes, progress=progress)
    if path is not None:
        belief.save(path)
    return belief
