"""Driving-and-Rescuing rules, written from docs/tasks.md."""

from __future__ import annotations

import pytest
import torch

from amuled_ma.tasks.driving import Driving

STRAIGHT, RIGHT, LEFT = 0, 1, 2


def quiet(num_envs: int = 1, **kw) -> Driving:
    """A road where nothing spawns, to test hand-placed objects."""
    task = Driving(num_envs, p_car=0.0, p_grandma=0.0, **kw)
    task.reset(seed=0)
    return task


def step(task: Driving, action: int):
    return task.step(torch.full((task.num_envs,), action, dtype=torch.int64))


def test_initial_state():
    task = Driving(1, seed=0)
    obs = task.reset()
    assert obs[0].tolist() == [-1, -1, -1, -1, -1, -1, 0, 0, 1, 0, 0]
    assert task.lane.item() == 2


def test_observation_layout_and_missing_lanes():
    task = quiet()
    task.place("car", 2, 6)
    task.place("grandma", 2, 5)
    task.place("car", 1, 3)  # left of lane 2
    task.place("grandma", 3, 8)  # right of lane 2
    task.place("car", 3, 7)
    task.place("car", 3, 4)  # the nearer one of lane 3 is observed
    assert task.obs[0].tolist() == [6, 5, 3, -1, 4, 8, 0, 0, 1, 0, 0]
    task.set_lane(0)
    assert task.obs[0].tolist()[:6] == [-1, -1, -2, -2, 3, -1]
    assert task.obs[0].tolist()[6:] == [1, 0, 0, 0, 0]
    task.set_lane(4)
    assert task.obs[0].tolist()[:6] == [-1, -1, 4, 8, -2, -2]


def test_objects_approach_at_their_speeds():
    task = quiet()
    task.place("car", 2, 8)
    task.place("grandma", 2, 8)
    seen = []
    for _ in range(3):
        obs, *_ = step(task, STRAIGHT)
        seen.append(obs[0, :2].tolist())
    assert seen == [[7, 5], [6, 2], [5, -1]]  # cars 1 unit per step, grandmas 3


def test_collision_and_rescue_in_the_current_lane():
    task = quiet(shaping_coef=1.0)
    task.place("car", 2, 1)
    task.place("grandma", 2, 2)
    obs, reward, term, trunc, info = step(task, STRAIGHT)
    assert info["collisions"].item() == 1 and info["rescues"].item() == 1
    assert info["r_env"].item() == -20 + 0.5
    assert info["r_shaping"].item() == 400 + 20
    assert reward.item() == pytest.approx(-19.5 + 420)
    assert not term.item() and not trunc.item()
    # both reached distance <= 0 and were removed
    assert task.objects() == {"car": [], "grandma": []}
    assert obs[0, :2].tolist() == [-1, -1]


def test_objects_in_other_lanes_do_not_hit_but_are_removed():
    task = quiet()
    task.place("car", 3, 1)  # the lane to the right
    task.place("grandma", 4, 2)
    task.place("car", 1, 2)
    _, _, _, _, info = step(task, STRAIGHT)
    assert info["collisions"].item() == 0 and info["rescues"].item() == 0
    # passed objects leave every lane; the others move on
    assert task.objects() == {"car": [(1, 1)], "grandma": []}


def test_lane_change_counts_current_and_target_lane():
    # a car at distance 1 in the target lane: changing into it collides
    task = quiet()
    task.place("car", 3, 1)
    _, _reward, _, _, info = step(task, RIGHT)
    assert info["collisions"].item() == 1 and task.lane.item() == 3
    assert info["lane_changes"].item()
    assert info["r_env"].item() == -20.0  # no straight bonus
    assert info["r_shaping"].item() == 0.0  # the lane changed
    # a car at distance 1 in the current lane: leaving it still collides
    task = quiet()
    task.place("car", 2, 1)
    _, _, _, _, info = step(task, LEFT)
    assert info["collisions"].item() == 1 and task.lane.item() == 1
    # grandmas: both lanes count too
    task = quiet()
    task.place("grandma", 1, 2)
    _, _, _, _, info = step(task, LEFT)
    assert info["rescues"].item() == 1
    task = quiet()
    task.place("grandma", 2, 2)
    _, _, _, _, info = step(task, RIGHT)
    assert info["rescues"].item() == 1
    # not into the lane on the other side
    task = quiet()
    task.place("car", 1, 1)
    _, _, _, _, info = step(task, RIGHT)
    assert info["collisions"].item() == 0


def test_collision_counting_over_an_episode_and_edges():
    task = quiet()
    task.set_lane(4)
    task.place("car", 4, 1)
    _, _, _, _, info = step(task, RIGHT)  # clipped: stays in lane 4, only lane 4 counts
    assert task.lane.item() == 4
    assert info["collisions"].item() == 1
    assert not info["lane_changes"].item()
    assert info["r_env"].item() == -20.0  # the action was not "straight"
    assert info["r_shaping"].item() == 20.0  # but the lane is the same
    task.set_lane(0)
    task.place("car", 0, 1)
    _, _, _, _, info = step(task, LEFT)
    assert task.lane.item() == 0 and info["collisions"].item() == 1


def test_grandma_at_distance_5_is_not_rescued_yet():
    task = quiet()
    task.place("grandma", 2, 5)
    _, _, _, _, info = step(task, STRAIGHT)
    assert info["rescues"].item() == 0
    assert task.objects()["grandma"] == [(2, 2)]
    _, _, _, _, info = step(task, STRAIGHT)
    assert info["rescues"].item() == 1


def test_episode_is_300_steps_with_metrics():
    task = Driving(1, seed=1, shaping_coef=0.5)
    task.reset()
    actions = [STRAIGHT, RIGHT, LEFT, LEFT, STRAIGHT]
    total = {"collisions": 0, "rescues": 0, "lane_changes": 0}
    ret = 0.0
    for t in range(300):
        _, reward, term, trunc, info = step(task, actions[t % 5])
        assert not term.item()
        for k in total:
            total[k] += int(info[k].item())
        ret += reward.item()
        assert trunc.item() == (t == 299)
    ep = info["episode"]
    assert ep["done"].item() and ep["length"].item() == 300
    for k, v in total.items():
        assert ep[k].item() == v
    assert ep["return"].item() == pytest.approx(ret, rel=1e-5)
    assert task.lane.item() == 2 and task.episode_steps.item() == 0  # auto-reset


def test_spawn_rates_within_statistical_tolerance():
    n, steps = 4096, 60
    task = Driving(n, seed=123)
    task.reset()
    cars = torch.zeros(5)
    grandmas = torch.zeros(5)
    both = 0
    for _ in range(steps):
        step(task, STRAIGHT)
        road = task.road()
        new_car = road["car"][:, :, 8]  # objects at distance 8 appeared on this step
        new_gm = road["grandma"][:, :, 8]
        assert new_car.sum(1).max() <= 1 and new_gm.sum(1).max() <= 1
        cars += new_car.sum(0)
        grandmas += new_gm.sum(0)
        both += int((new_car.any(1) & new_gm.any(1)).sum())
    trials = n * steps
    for count, p in ((cars.sum(), 0.16), (grandmas.sum(), 0.09), (both, 0.16 * 0.09)):
        sd = (p * (1 - p) / trials) ** 0.5
        assert abs(float(count) / trials - p) < 5 * sd
    # uniform lanes: chi-square with 4 degrees of freedom, 0.1% critical value 18.47
    for counts in (cars, grandmas):
        expected = counts.sum() / 5
        chi2 = float(((counts - expected) ** 2 / expected).sum())
        assert chi2 < 18.47


def test_same_seed_same_road_different_seed_different_road():
    a, b, c = Driving(16, seed=7), Driving(16, seed=7), Driving(16, seed=8)
    oa, ob, oc = a.reset(), b.reset(), c.reset()
    gen = torch.Generator().manual_seed(0)
    differ = False
    for _ in range(50):
        act = torch.randint(0, 3, (16,), generator=gen)
        oa, ra, *_ = a.step(act)
        ob, rb, *_ = b.step(act)
        oc, *_ = c.step(act)
        assert torch.equal(oa, ob) and torch.equal(ra, rb)
        differ |= not torch.equal(oa, oc)
    assert differ


def test_copy_i_equals_seed_plus_i():
    wide = Driving(6, seed=40)
    wide.reset()
    single = Driving(1, seed=43)
    single.reset()
    for _ in range(200):
        ow, *_ = wide.step(torch.zeros(6, dtype=torch.int64))
        os_, *_ = single.step(torch.zeros(1, dtype=torch.int64))
        assert torch.equal(ow[3], os_[0])


def test_place_rejects_impossible_objects():
    task = quiet()
    with pytest.raises(ValueError, match="distance"):
        task.place("grandma", 2, 4)
    with pytest.raises(ValueError, match="lane"):
        task.place("car", 5, 3)
    with pytest.raises(ValueError, match="kind"):
        task.place("cat", 2, 3)
    task.place("car", 1, 4)
    with pytest.raises(ValueError, match="another car is already at distance 4"):
        task.place("car", 3, 4)
    task.place("car", 1, 4)  # the same object again is fine
