"""What both demonstrators' play shares: per-episode streams, action draws, pair counting.

Episode ``e`` of a demonstrator seeded ``s`` plays on the task copy seeded ``b_s + e`` and
draws its own choices from the counter-based stream (`rng`) of seed
``c_s + e``, where ``b_s`` and ``c_s`` are two hashes of ``s`` (so the episodes of seeds ``s``
and ``s + 1`` share no stream). The counts therefore depend on ``seed`` and the episode
indices only, not on how many episodes are played side by side.
"""

from __future__ import annotations

import torch

from amuled_ma.monitor.progress import Progress
from amuled_ma.tasks import rng

__all__ = ["PairCounter", "episode_streams", "progress_bar", "sample", "task_seed", "uniforms"]

_TASK_STREAMS, _CHOICE_STREAMS = 0, 1  # purposes of the per-episode random streams


def _base_seed(seed: int, purpose: int) -> int:
    """Base of the per-episode seeds of ``seed`` for one purpose (0 task, 1 choices).

    Episode ``e`` uses ``base + e``. The base is a hash of ``seed``, so the episodes of seeds
    ``s`` and ``s + 1`` do not share streams (``seed + e`` would shift them by one).
    """
    return rng.splitmix64(rng.splitmix64(seed) ^ purpose) >> 2


def task_seed(seed: int, first: int) -> int:
    """Return the seed of a task whose copy ``i`` plays episode ``first + i``.

    Args:
        seed: The demonstrator's seed.
        first: Index of the episode copy 0 plays.

    Returns:
        The task's base seed (copy ``i`` is the task of seed ``task_seed + i``).

    """
    return _base_seed(seed, _TASK_STREAMS) + first


def episode_streams(seed: int, first: int, count: int, device: torch.device) -> torch.Tensor:
    """Return the keys of the choice streams of episodes ``first..first+count-1``.

    Args:
        seed: The demonstrator's seed.
        first: Index of the first episode.
        count: Number of episodes.
        device: Torch device of the keys.

    Returns:
        int64 ``[count]``, for `uniforms`.

    """
    return rng.copy_keys(_base_seed(seed, _CHOICE_STREAMS) + first, count, device)


def uniforms(keys: torch.Tensor, start: int, count: int) -> torch.Tensor:
    """Return draws ``start..start+count-1`` of each stream as float64 in ``[0, 1)``.

    Args:
        keys: Stream keys (`episode_streams`), int64 ``[N]``.
        start: First draw number.
        count: Draws per stream.

    Returns:
        float64 ``[N, count]``.

    """
    return rng.uniform53(rng.draws(keys, start, count))


def sample(weights: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Draw one action per row with probability ``weights / weights.sum()`` (inverse CDF).

    Args:
        weights: Non-negative weights ``[N, num_actions]``.
        u: One uniform in ``[0, 1)`` per row, ``[N]``.

    Returns:
        int64 actions ``[N]``.

    """
    cdf = weights.cumsum(1)
    picked = (cdf <= (u * cdf[:, -1])[:, None]).sum(1)
    return picked.clamp_(max=weights.shape[1] - 1)


class PairCounter:
    """Accumulates ``(observation key, action)`` pairs, deduplicating now and then.

    Args:
        num_actions: The task's number of actions.

    """

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
