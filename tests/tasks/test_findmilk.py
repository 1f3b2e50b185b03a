"""FindMilk rules, written from docs/tasks.md."""

from __future__ import annotations

import pytest
import torch

from amuled_ma.tasks.findmilk import CRYING, SLEEPING, FindMilk

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def run(task: FindMilk, actions: list[int]):
    """Step copy 0 (of a 1-copy task) through ``actions``; return the list of step results."""
    out = []
    for a in actions:
        out.append(task.step(torch.tensor([a])))
    return out


def obs_list(obs: torch.Tensor) -> list[float]:
    return obs[0].tolist()


def test_initial_observation_paper_layout():
    task = FindMilk(1, seed=0)
    obs = task.reset()
    # robot (0,0), milk (7,7), nearest crying (2,2) (d2=8), nearest sleeping (1,1) (d2=2)
    assert obs_list(obs) == [0, 0, 7, 7, 2, 2, 1, 1]
    assert obs.dtype == torch.float32 and obs.shape == (1, 8)
    assert task.crying_left().item() == 5 and task.sleeping_left().item() == 6


def test_walls_keep_the_robot_in_place_and_cost_a_step():
    task = FindMilk(1)
    task.reset()
    for a in (DOWN, LEFT):
        obs, reward, term, trunc, _info = task.step(torch.tensor([a]))
        assert obs_list(obs)[:2] == [0, 0]
        assert reward.item() == -1.0 and not term.item() and not trunc.item()
    assert task.episode_steps.item() == 2
    # the far walls: go to (7, 0) along y = 0 ... then right again stays
    task.reset()
    run(task, [RIGHT] * 7)
    obs, *_ = task.step(torch.tensor([RIGHT]))
    assert obs_list(obs)[:2] == [7, 0]
    obs, *_ = task.step(torch.tensor([DOWN]))
    assert obs_list(obs)[:2] == [7, 0]


def test_moves_follow_the_axes():
    task = FindMilk(1)
    task.reset()
    ((obs, *_),) = run(task, [UP])
    assert obs_list(obs)[:2] == [0, 1]
    ((obs, *_),) = run(task, [RIGHT])
    assert obs_list(obs)[:2] == [1, 1]
    ((obs, *_),) = run(task, [DOWN])
    assert obs_list(obs)[:2] == [1, 0]
    ((obs, *_),) = run(task, [LEFT])
    assert obs_list(obs)[:2] == [0, 0]


def test_entering_a_sleeping_baby_wakes_and_removes_it():
    task = FindMilk(1, shaping_coef=1.0)
    task.reset()
    run(task, [UP])
    obs, reward, _, _, info = task.step(torch.tensor([RIGHT]))  # (1, 1): sleeping baby
    assert info["sleeping_woken"].item() and not info["crying_pacified"].item()
    assert info["r_env"].item() == -1.0 and info["r_shaping"].item() == -1.0
    assert reward.item() == -2.0
    assert task.sleeping_left().item() == 5
    assert (1, 1) not in task.baby_positions()["sleeping"]
    # the nearest sleeping baby is now another one: from (1,1): (3,3) d2=8, (4,0) d2=10
    assert obs_list(obs)[6:] == [3, 3]
    # leaving and re-entering the cell does not count again
    run(task, [LEFT])
    _, _, _, _, info = task.step(torch.tensor([RIGHT]))
    assert not info["sleeping_woken"].item()
    assert task.sleeping_left().item() == 5


def test_entering_a_crying_baby_pacifies_and_removes_it():
    task = FindMilk(1, shaping_coef=2.0)
    task.reset()
    run(task, [RIGHT, RIGHT, UP])  # (2, 1)
    obs, reward, _, _, info = task.step(torch.tensor([UP]))  # (2, 2): crying baby
    assert info["crying_pacified"].item() and not info["sleeping_woken"].item()
    assert info["r_shaping"].item() == 1.0
    assert reward.item() == pytest.approx(-1.0 + 2.0)
    assert task.crying_left().item() == 4
    # nearest crying from (2,2) is now (2,3) at distance 1
    assert obs_list(obs)[4:6] == [2, 3]
    # variables of the state prompt carry the count, which the observation lacks
    assert task.prompt_variables()[0]["num_crying"] == 4


def test_shortest_path_is_14_steps_and_reaching_the_milk_pays_20():
    task = FindMilk(1, shaping_coef=1.0)
    task.reset()
    results = run(task, [UP] * 7 + [RIGHT] * 7)  # along x = 0, then y = 7
    for _obs, _reward, term, trunc, info in results[:-1]:
        assert not term.item() and not trunc.item()
        assert info["r_env"].item() == -1.0
    obs, _reward, term, trunc, info = results[-1]
    assert term.item() and not trunc.item()
    assert info["r_env"].item() == 20.0
    assert info["final_obs"][0, :2].tolist() == [7, 7]
    # auto-reset: the returned observation is the next episode's first one
    assert obs_list(obs) == [0, 0, 7, 7, 2, 2, 1, 1]
    ep = info["episode"]
    assert ep["done"].item() and ep["length"].item() == 14 and ep["steps_to_milk"].item() == 14
    assert ep["reached_milk"].item()
    # (6, 7) is the only baby on this path: one crying baby pacified
    assert ep["crying_pacified"].item() == 1 and ep["sleeping_woken"].item() == 0
    assert ep["return_env"].item() == pytest.approx(13 * -1 + 20)
    assert ep["return_shaping"].item() == pytest.approx(1.0)
    assert ep["return"].item() == pytest.approx(8.0)
    # the next episode starts fresh
    assert task.crying_left().item() == 5 and task.episode_steps.item() == 0


def test_no_path_is_shorter_than_14_steps():
    # 4**6 copies take every 6-step action sequence: none reaches x + y > 6, so (with one unit
    # per step) no sequence reaches (7, 7) in fewer than 14 steps
    task = FindMilk(4**6)
    task.reset()
    seqs = torch.cartesian_prod(*[torch.arange(4)] * 6)  # every 6-step sequence
    reached = torch.zeros(4**6, dtype=torch.bool)
    for i in range(6):
        _, _, term, _, _ = task.step(seqs[:, i])
        reached |= term
    assert not reached.any()
    obs = task.obs
    assert (obs[:, 0] + obs[:, 1]).max().item() == 6


def test_truncation_after_300_steps():
    task = FindMilk(1)
    task.reset()
    for _ in range(299):
        _, _, term, trunc, _ = task.step(torch.tensor([LEFT]))
        assert not term.item() and not trunc.item()
    _obs, _, term, trunc, info = task.step(torch.tensor([LEFT]))
    assert trunc.item() and not term.item()
    ep = info["episode"]
    assert ep["length"].item() == 300 and not ep["reached_milk"].item()
    assert ep["steps_to_milk"].item() == 300
    assert ep["return_env"].item() == -300.0


def test_reaching_the_milk_on_the_last_step_is_termination():
    task = FindMilk(1, max_steps=14)
    task.reset()
    *_, (_obs, _, term, trunc, _) = run(task, [RIGHT] * 7 + [UP] * 7)
    assert term.item() and not trunc.item()


def test_nearest_baby_tie_break_smallest_x_then_y():
    # from (6, 5): sleeping (5, 5) and (6, 6) are both at distance 1 -> (5, 5) (smaller x)
    task = FindMilk(1)
    task.reset()
    run(task, [RIGHT] * 6 + [UP] * 5)  # along y=0 (wakes (4,0)), then x=6 up to (6,5)
    obs = task.obs
    assert obs_list(obs)[:2] == [6, 5]
    assert obs_list(obs)[6:] == [5, 5]
    # from (5, 7)... crying (5, 6) and (6, 7) both at distance 1 -> (5, 6)
    task.reset()
    run(task, [UP] * 7 + [RIGHT] * 5)
    assert obs_list(task.obs)[:2] == [5, 7]
    assert obs_list(task.obs)[4:6] == [5, 6]
    # from (4, 2): crying (2, 2) and (4, 4) both at distance 2 -> (2, 2) (smaller x)
    task.reset()
    run(task, [RIGHT] * 3 + [UP] * 2 + [RIGHT])  # (3,0) -> (3,2) -> (4,2), no baby touched
    assert obs_list(task.obs)[:2] == [4, 2] and task.crying_left().item() == 5
    assert obs_list(task.obs)[4:6] == [2, 2]


def test_none_left_is_reported_as_origin():
    task = FindMilk(1)
    task.reset()
    # pacify every crying baby: (2,2), (2,3), (4,4), (5,6), (6,7)
    path = [RIGHT, RIGHT, UP, UP, UP, RIGHT, RIGHT, UP, RIGHT, UP, UP, RIGHT, UP]
    run(task, path)
    assert task.crying_left().item() == 0, task.render_ansi()
    assert obs_list(task.obs)[4:6] == [0, 0]
    assert task.prompt_variables()[0]["crying_around"] == 0


def test_lookup_tables_agree_with_direct_search():
    task = FindMilk(2048, seed=3)
    task.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(150):
        task.step(torch.randint(0, 4, (2048,), generator=gen))
        fast = task._nearest_cells()
        task.use_tables = False
        slow = task._nearest_cells()
        task.use_tables = True
        assert torch.equal(fast[0], slow[0]) and torch.equal(fast[1], slow[1])


def test_random_layout_distinct_cells_and_reproducible():
    task = FindMilk(256, seed=11, layout="random")
    obs = task.reset()
    again = FindMilk(256, seed=11, layout="random").reset()
    assert torch.equal(obs, again)
    other = FindMilk(256, seed=12, layout="random").reset()
    assert not torch.equal(obs, other)
    for i in range(0, 256, 17):
        babies = task.baby_positions(i)
        start = tuple(obs[i, :2].int().tolist())
        milk = tuple(obs[i, 2:4].int().tolist())
        cells = [start, milk, *babies["crying"], *babies["sleeping"]]
        assert len(babies["crying"]) == len(CRYING) and len(babies["sleeping"]) == len(SLEEPING)
        assert len(set(cells)) == len(cells)
        assert (0, 0) not in babies["crying"] + babies["sleeping"]
    # layouts are redrawn at every reset and vary across copies
    starts = {tuple(r) for r in obs[:, :2].int().tolist()}
    assert len(starts) > 30


def test_random_layout_rules_hold():
    task = FindMilk(64, seed=5, layout="random", shaping_coef=1.0)
    task.reset()
    gen = torch.Generator().manual_seed(1)
    for _ in range(400):
        before_c, before_s = task.crying_left().clone(), task.sleeping_left().clone()
        _, _reward, term, _, info = task.step(torch.randint(0, 4, (64,), generator=gen))
        done = info["episode"]["done"]
        pac, wok = info["crying_pacified"], info["sleeping_woken"]
        assert torch.all(info["r_shaping"] == pac.float() - wok.float())
        assert torch.all(info["r_env"] == torch.where(term, 20.0, -1.0))
        keep = ~done
        assert torch.equal(task.crying_left()[keep], (before_c - pac.long())[keep])
        assert torch.equal(task.sleeping_left()[keep], (before_s - wok.long())[keep])
        assert torch.all(task.crying_left()[done] == 5)
