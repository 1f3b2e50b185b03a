"""The paper's synthetic "human feedback" baseline: a rule-obeying belief over actions.

The rules are in docs/tasks.md, "Synthetic human belief"; the differences to the authors'
scripts in "Differences to the authors' code".
"""

from __future__ import annotations

import numpy as np

from amuled_ma.tasks.names import canonical_name

__all__ = ["human_belief"]

_MOVES = np.array([[0, 1], [0, -1], [-1, 0], [1, 0]], dtype=np.float64)  # up, down, left, right
_GRID_MAX = 7.0
_MAX_DISTANCE = 24.0


def _as_obs(obs: object, dim: int) -> np.ndarray:
    values = np.asarray(obs, dtype=np.float64)
    if values.ndim == 0 or values.shape[-1] != dim:
        raise ValueError(f"obs: expected shape (..., {dim}), got {values.shape}")
    return values


def _findmilk(obs: np.ndarray, sleeping: object = None) -> np.ndarray:
    pos, milk, cry, sleep = obs[..., 0:2], obs[..., 2:4], obs[..., 4:6], obs[..., 6:8]
    nxt = np.clip(pos[..., None, :] + _MOVES, 0.0, _GRID_MAX)  # [..., 4, 2]
    if sleeping is None:
        around = (sleep != 0).any(-1)[..., None]
        on_sleep = (nxt == sleep[..., None, :]).all(-1) & around
    else:
        babies = np.asarray(sleeping, dtype=np.float64)  # [..., K, 2], negative = absent
        if babies.ndim < 2 or babies.shape[-1] != 2 or babies.shape[:-2] != obs.shape[:-1]:
            raise ValueError(
                f"sleeping: expected shape {(*obs.shape[:-1], 'K', 2)}, got {babies.shape}"
            )
        present = (babies >= 0).all(-1)  # [..., K]
        same = (nxt[..., :, None, :] == babies[..., None, :, :]).all(-1)  # [..., 4, K]
        on_sleep = (same & np.expand_dims(present, -2)).any(-1)
    on_milk = (nxt == milk[..., None, :]).all(-1)
    crying = (cry != 0).any(-1, keepdims=True)
    d = np.abs(nxt - cry[..., None, :]).sum(-1)
    toward_cry = np.where(
        crying & (d < _MAX_DISTANCE), 20.0 * (_MAX_DISTANCE - d) / _MAX_DISTANCE, 5.0
    )
    weights = np.where(on_sleep, 1.0, np.where(on_milk, 20.0, toward_cry))
    return weights / weights.sum(-1, keepdims=True)


def _driving(obs: np.ndarray) -> np.ndarray:
    # target lane of straight, right, left: (car, grandma) columns of the observation
    car = obs[..., [0, 4, 2]]
    grandma = obs[..., [1, 5, 3]]
    missing = car == -2
    car_near = (car >= 0) & (car <= 1)
    grandma_near = (grandma >= 0) & (grandma <= 3)
    neutral = np.broadcast_to(np.array([5.0, 2.0, 2.0]), car.shape)
    weights = np.where(missing | car_near, 1.0, np.where(grandma_near, 20.0, neutral))
    return weights / weights.sum(-1, keepdims=True)


def human_belief(task_name: str, obs: object, *, sleeping: object = None) -> np.ndarray:
    """Return the synthetic human belief ``(..., num_actions)`` (float64, rows sum to 1).

    ``sleeping`` (FindMilk only) gives every remaining sleeping baby ``(..., K, 2)``, negative
    for absent ones, to check them all as the authors' script did.

    Raises:
        ValueError: Unknown task or ``obs`` / ``sleeping`` of the wrong shape.
    """
    name = canonical_name(task_name)
    if name == "findmilk":
        return _findmilk(_as_obs(obs, 8), sleeping)
    if sleeping is not None:
        raise ValueError("sleeping: only FindMilk has sleeping babies")
    return _driving(_as_obs(obs, 11))
