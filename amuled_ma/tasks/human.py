"""The paper's synthetic "human feedback" baseline: a rule-obeying belief over actions.

`human_belief` turns observations into probability vectors over the task's actions,
vectorised over any leading dimensions, from the observation alone.

FindMilk (the authors' ``algorithms/human_policy_milk.py``): for each
action take the next cell (a move into a wall keeps the cell), then its weight is

- 1 if the next cell holds a sleeping baby;
- else 20 if the next cell is the milk;
- else ``20 * (24 - d) / 24`` with ``d`` the Manhattan distance from the next cell to the
  nearest crying baby of the observation, or 5 when ``d >= 24`` or no crying baby is left.

The weights are normalised to sum to 1. Two deliberate differences to the authors' script:
the observation only shows the *nearest* sleeping baby, so "holds a sleeping baby" checks
that one (the authors looked up every remaining sleeping baby in the environment; pass
``sleeping=`` to do the same), and when no crying baby is left (observation ``(0, 0)``) the
weight is 5 rather than a distance to the cell ``(0, 0)``.

Driving (this project's rule; the authors' script learned a Q-table instead):
each action is judged by the lane it steers into (straight: the current lane, right:
lane+1, left: lane-1) and the observation of that lane:

- 1 if that lane does not exist or has a car within reach (distance 0..1: it would be hit
  on this step) — avoidance wins over rescue;
- else 20 if that lane has a grandma within reach (distance 0..3);
- else 5 for straight and 2 for a lane change (going straight is preferred).

The weights are normalised to sum to 1.
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
    """Return the synthetic human belief over actions for each observation.

    Args:
        task_name: ``"findmilk"`` or ``"driving"`` (or a Gymnasium id).
        obs: Observations, shape ``(..., obs_dim)`` (numpy array, list or CPU tensor).
        sleeping: FindMilk only, optional: every remaining sleeping baby, shape
            ``(..., K, 2)`` with negative coordinates for absent ones, to check every
            sleeping baby instead of the observation's nearest one (the authors' script).

    Returns:
        float64 array ``(..., num_actions)``, each row summing to 1.

    Raises:
        ValueError: Unknown task or ``obs`` / ``sleeping`` of the wrong shape.

    """
    name = canonical_name(task_name)
    if name == "findmilk":
        return _findmilk(_as_obs(obs, 8), sleeping)
    if sleeping is not None:
        raise ValueError("sleeping: only FindMilk has sleeping babies")
    return _driving(_as_obs(obs, 11))
