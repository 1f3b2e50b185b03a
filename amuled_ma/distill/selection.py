"""Which new states to ask when the budget admits fewer than arrived (pure numpy)."""

from __future__ import annotations

import numpy as np


def disagreement(predictions: np.ndarray, members: np.ndarray | None = None) -> np.ndarray:
    """Per state, the mean over members and networks of ``0.5 * sum_a |p_e(a) - mean_e p(a)|``.

    ``members``: ``(K,)`` bool, the members to average over (default all; none: 1 each).
    """
    predictions = np.asarray(predictions, dtype=np.float64)
    mean = predictions.mean(0, keepdims=True)
    tv = 0.5 * np.abs(predictions - mean).sum(-1)  # (E, N, K)
    if members is not None:
        members = np.asarray(members, dtype=bool)
        if not members.any():
            return np.ones(predictions.shape[1])
        tv = tv[:, :, members]
    return tv.mean(axis=(0, 2))


def choose_uncertain(
    candidates: np.ndarray,
    count: int,
    asked: np.ndarray,
    spread: np.ndarray | None = None,
) -> list[int]:
    """Pick ``count`` candidates greedily by disagreement plus novelty; indices in chosen order.

    Novelty is ``1 - exp(-d / sqrt(D))``, ``d`` the standardised distance to the nearest state
    asked or chosen earlier in the batch; ``spread`` is None before the first fit (1 each).
    """
    candidates = np.asarray(candidates, dtype=np.float64)
    n = len(candidates)
    count = min(int(count), n)
    if count <= 0:
        return []
    asked = np.asarray(asked, dtype=np.float64).reshape(-1, candidates.shape[1])
    union = np.concatenate([candidates, asked])  # both scaled by the union's mean and spread
    std = union.std(0)
    std = np.where(std > 1e-9, std, 1.0)
    x, seen = (candidates - union.mean(0)) / std, (asked - union.mean(0)) / std
    scale = np.sqrt(max(1, x.shape[1]))
    nearest = np.full(n, np.inf)
    if len(seen):
        nearest = np.sqrt(((x[:, None, :] - seen[None, :, :]) ** 2).sum(-1)).min(1)
    base = np.ones(n) if spread is None else np.asarray(spread, dtype=np.float64).reshape(n)
    chosen: list[int] = []
    free = np.ones(n, dtype=bool)
    for _ in range(count):
        novelty = np.where(np.isinf(nearest), 1.0, 1.0 - np.exp(-nearest / scale))
        score = np.where(free, base + novelty, -np.inf)
        pick = int(np.argmax(score))  # the first of equal scores
        chosen.append(pick)
        free[pick] = False
        nearest = np.minimum(nearest, np.sqrt(((x - x[pick]) ** 2).sum(-1)))
    return chosen


def choose_random(n: int, count: int, rng: np.random.Generator) -> list[int]:
    """Pick ``count`` of ``n`` states uniformly without replacement (in drawn order)."""
    count = min(int(count), int(n))
    if count <= 0:
        return []
    return [int(i) for i in rng.choice(n, size=count, replace=False)]
