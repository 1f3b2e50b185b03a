"""What both demonstrators' play shares: per-episode streams, action draws, pair counting.

Episode ``e`` of seed ``s`` plays the task seeded ``b_s + e`` and draws from the stream of
``c_s + e`` (``b_s``, ``c_s``: hashes of ``s``), so the counts do not depend on batching.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from amuled_ma.monitor.progress import Progress
from amuled_ma.tasks import get_task, rng
from amuled_ma.tasks.base import check_int
from amuled_ma.tasks.demonstrators.table import DemonstratorBelief, demonstrator_settings

__all__ = ["PairCounter", "episode_streams", "play_counted", "sample", "task_seed", "uniforms"]

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
