"""Which new states to ask, when the budget admits fewer than arrived.

- ``uncertainty``: a state's score is the ensemble's **disagreement** (for each member the
  model answers, the mean total-variation distance of the networks' beliefs to their
  mean, averaged over those members; 1, the largest, before the first fit) plus its
  **novelty** ``1 - exp(-d / sqrt(D))``, where ``d`` is the Euclidean distance of its
  standardised observation to the nearest state already asked (or chosen earlier in the
  same batch) and ``D`` the observation's length (1 when nothing was asked yet). Both terms
  lie in ``[0, 1]``. States are chosen one at a time, best score first (the earliest in
  the batch on a tie), each choice making its neighbours less novel, so one batch does
  not spend its share on near-duplicates.
- ``random``: a uniform sample without replacement from a seeded generator (the
  baseline of the budget ablation); its state is kept with the budget, so a resumed run
  draws what an uninterrupted one would.

Pure numpy; the ensemble's predictions are passed in.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

#: The selection rules of ``[feedback.distill].selection``.
Selection = Literal["uncertainty", "random"]
SELECTIONS: tuple[str, ...] = ("uncertainty", "random")


def disagreement(predictions: np.ndarray, members: np.ndarray | None = None) -> np.ndarray:
    """The ensemble's disagreement per state, in ``[0, 1]``.

    Args:
        predictions: ``(E, N, K, A)`` every network's belief per state and member.
        members: ``(K,)`` bool, the members to average over (default: all).

    Returns:
        ``(N,)``: mean over the chosen members and the networks of the total-variation
        distance ``0.5 * sum_a |p_e(a) - mean_e p(a)|``.

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


def standardise(candidates: np.ndarray, asked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both sets of observations scaled by the mean and spread of their union."""
    candidates = np.asarray(candidates, dtype=np.float64)
    asked = np.asarray(asked, dtype=np.float64).reshape(-1, candidates.shape[1])
    union = np.concatenate([candidates, asked])
    mean = union.mean(0)
    std = union.std(0)
    std = np.where(std > 1e-9, std, 1.0)
    return (candidates - mean) / std, (asked - mean) / std


def choose_uncertain(
    candidates: np.ndarray,
    count: int,
    asked: np.ndarray,
    spread: np.ndarray | None = None,
) -> list[int]:
    """Pick ``count`` states by disagreement plus novelty (see the module).

    Args:
        candidates: ``(N, D)`` observations of the states that may be asked.
        count: How many to pick (at most ``N``).
        asked: ``(M, D)`` observations of the states asked before.
        spread: ``(N,)`` the ensemble's disagreement; None before the first fit (1 each).

    Returns:
        Indices into ``candidates``, in the order chosen.

    """
    candidates = np.asarray(candidates, dtype=np.float64)
    n = len(candidates)
    count = min(int(count), n)
    if count <= 0:
        return []
    x, seen = standardise(candidates, asked)
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
