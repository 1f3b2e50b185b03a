"""What both demonstrators' play shares: per-episode streams, action draws, pair counting.

Episode ``e`` of seed ``s`` plays the task seeded ``b_s + e`` and draws from the stream of
``c_s + e`` (``b_s``, ``c_s``: hashes of ``s``), so the counts do not depend on batching.
"""

from __future__ import annotations

import torch

from amuled_ma.monitor.progress import Progress
from amuled_ma.tasks import rng

__all__ = ["PairCounter", "episode_streams", "progress_bar", "sample", "task_seed", "uniforms"]

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


def progress_bar(total: int, desc: str, enabled: bool) -> Progress:
    """The progress of ``total`` episodes: a bar when ``enabled``, else plain lines past 10 s."""
    return Progress(desc, total, bar=enabled, unit="episode")
