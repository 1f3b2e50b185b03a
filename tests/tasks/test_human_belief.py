"""The synthetic "human" belief, checked against values computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.tasks.findmilk import FindMilk
from amuled_ma.tasks.human import human_belief


def norm(*w: float) -> list[float]:
    return [x / sum(w) for x in w]


def test_findmilk_start():
    # up (0,1): d=|0-2|+|1-2|=3 -> 20*21/24=17.5; down/left hit the wall (0,0): d=4 -> 20*20/24;
    # right (1,0): d=3 -> 17.5
    got = human_belief("findmilk", np.array([0, 0, 7, 7, 2, 2, 1, 1]))
    np.testing.assert_allclose(got, norm(17.5, 50 / 3, 50 / 3, 17.5))


def test_findmilk_sleeping_baby_and_milk():
    # robot (1,0): up onto the sleeping baby (1,1) -> 1; down (wall, 1,0): d=3 -> 17.5;
    # left (0,0): d=4 -> 50/3; right (2,0): d=2 -> 20*22/24
    got = human_belief("findmilk", [1, 0, 7, 7, 2, 2, 1, 1])
    np.testing.assert_allclose(got, norm(1, 17.5, 50 / 3, 55 / 3))
    # robot (7,6), crying (6,7), sleeping (6,6): up onto the milk -> 20; down (7,5): d=3 -> 17.5;
    # left onto the sleeping baby -> 1; right (wall, 7,6): d=2 -> 55/3
    got = human_belief("findmilk", [7, 6, 7, 7, 6, 7, 6, 6])
    np.testing.assert_allclose(got, norm(20, 17.5, 1, 55 / 3))


def test_findmilk_no_crying_baby_left_is_flat():
    got = human_belief("findmilk", [3, 3, 7, 7, 0, 0, 5, 5])
    np.testing.assert_allclose(got, [0.25] * 4)


def test_findmilk_every_sleeping_baby_when_given():
    # robot (6,5): sleeping (5,5) left and (6,6) up tie; the observation shows (5,5) only
    obs = np.array([6, 5, 7, 7, 5, 6, 5, 5], dtype=np.float32)
    d = {"up": 1, "down": 3, "right": 3}  # Manhattan distances to the crying baby (5,6)
    w = {k: 20 * (24 - v) / 24 for k, v in d.items()}
    np.testing.assert_allclose(
        human_belief("findmilk", obs), norm(w["up"], w["down"], 1, w["right"])
    )
    sleeping = np.array([[5, 5], [6, 6], [-1, -1]])
    np.testing.assert_allclose(
        human_belief("findmilk", obs, sleeping=sleeping), norm(1, w["down"], 1, w["right"])
    )


def test_findmilk_vectorised_over_leading_dims_and_env_state():
    task = FindMilk(6, seed=0)
    task.reset()
    obs = task.obs.numpy()
    batch = np.stack([obs, obs])  # (2, 6, 8)
    got = human_belief("findmilk", batch)
    assert got.shape == (2, 6, 4)
    np.testing.assert_allclose(got.sum(-1), 1.0)
    np.testing.assert_allclose(got[1, 3], human_belief("findmilk", obs[3]))
    full = human_belief("findmilk", obs, sleeping=task.sleeping_positions().numpy())
    assert full.shape == (6, 4)


def test_driving_rules():
    # lane 2: car at 1 in the current lane (avoid), grandma at 2 on the left (rescue),
    # right lane car at 5 / grandma at 8 (neutral change)
    obs = [1, -1, -1, 2, 5, 8, 0, 0, 1, 0, 0]
    np.testing.assert_allclose(human_belief("driving", obs), norm(1, 2, 20))
    # lane 0, empty road: straight 5, right 2, left does not exist 1
    obs = [-1, -1, -2, -2, -1, -1, 1, 0, 0, 0, 0]
    np.testing.assert_allclose(human_belief("Driving", obs), norm(5, 2, 1))
    # grandma within reach but a car too: avoidance wins
    obs = [-1, -1, 0, 2, -1, 3, 0, 1, 0, 0, 0]  # left lane car at 0 (would hit), right grandma 3
    np.testing.assert_allclose(human_belief("driving", obs), norm(5, 20, 1))


def test_bad_shapes():
    with pytest.raises(ValueError, match="obs"):
        human_belief("findmilk", np.zeros(11))
    with pytest.raises(ValueError, match="obs"):
        human_belief("driving", np.zeros((3, 8)))
    with pytest.raises(ValueError, match="sleeping"):
        human_belief("findmilk", np.zeros((2, 8)), sleeping=np.zeros((3, 6, 2)))
    with pytest.raises(ValueError, match="name"):
        human_belief("chess", np.zeros(8))
