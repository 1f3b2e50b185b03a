"""The authors' synthetic human demonstrators and their count beliefs.

Expected values are computed by hand (in comments) or with the authors' formulas written
out in plain Python here; the played demonstrators are checked against plain-Python
re-implementations of the authors' loops (dicts keyed by observation tuples, as in their
``human_policy_milk.py`` / ``human_policy_drive.py``) fed the same random numbers.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import Counter

import numpy as np
import pytest
import torch

from amuled_ma.tasks.demonstrators import (
    DemonstratorBelief,
    DemonstratorCacheError,
    cache_path,
    counts_to_belief,
    demonstrator_belief,
    demonstrator_settings,
    driving_human_reward,
    findmilk_weights,
    play_driving,
    play_findmilk,
    sarsa_update,
)
from amuled_ma.tasks.demonstrators.play import episode_streams, task_seed, uniforms
from amuled_ma.tasks.demonstrators.table import observation_bounds
from amuled_ma.tasks.driving import Driving
from amuled_ma.tasks.findmilk import FindMilk

START_OBS = [0, 0, 7, 7, 2, 2, 1, 1]


def authors_belief(count: list[float]) -> list[float]:
    """``finetune_moral_human.py`` lines 119-128, written out as the authors did."""
    total_cnt = sum(count)
    if total_cnt > 20:
        count = [p * 20 / total_cnt for p in count]
    total_cnt = sum(count)
    probs = [0.6 ** count[a] * (1 - 0.6) ** (total_cnt - count[a]) for a in range(len(count))]
    return [p / sum(probs) for p in probs]


# ---------------------------------------------------------------------- counts -> belief
def test_belief_of_small_counts():
    # [3, 0, 1]: 0.6^3*0.4 = 0.0864, 0.4^4 = 0.0256, 0.6*0.4^3 = 0.0384; sum 0.1504
    got = counts_to_belief(torch.tensor([3, 0, 1])).tolist()
    np.testing.assert_allclose(got, [0.0864 / 0.1504, 0.0256 / 0.1504, 0.0384 / 0.1504])
    np.testing.assert_allclose(got, [0.574, 0.170, 0.255], atol=5e-4)
    np.testing.assert_allclose(got, authors_belief([3, 0, 1]))


def test_belief_of_large_counts_is_rescaled_to_20():
    # [50, 10, 0] -> total 60 > 20 -> [50/3, 10/3, 0]; p ∝ 1.5^c: ratios 1.5^(-40/3), 1.5^(-50/3)
    got = counts_to_belief(torch.tensor([[50, 10, 0]]))[0].tolist()
    r1, r2 = 1.5 ** (-40 / 3), 1.5 ** (-50 / 3)
    np.testing.assert_allclose(got, [1 / (1 + r1 + r2), r1 / (1 + r1 + r2), r2 / (1 + r1 + r2)])
    np.testing.assert_allclose(got, [0.994, 0.0045, 0.0012], atol=5e-4)
    np.testing.assert_allclose(got, authors_belief([50, 10, 0]))
    # exactly 20 is not rescaled; far beyond 20 stays finite (log space)
    np.testing.assert_allclose(counts_to_belief([20, 0, 0]).tolist(), authors_belief([20, 0, 0]))
    huge = counts_to_belief([10**9, 1, 0])
    assert torch.isfinite(huge).all() and abs(float(huge.sum()) - 1) < 1e-12


def test_lookup_matches_observations_exactly():
    hand = DemonstratorBelief(
        "findmilk",
        torch.tensor([5, 900]),
        torch.tensor([[3, 0, 1, 0], [50, 10, 0, 0]]),
        demonstrator_settings("findmilk", seed=0),
    )
    # key of an observation: mixed radix 8 over the 8 entries (bounds 0..7)
    obs_5 = [0, 0, 0, 0, 0, 0, 0, 5]  # 5
    obs_900 = [0, 0, 0, 0, 1, 6, 0, 4]  # 1*512 + 6*64 + 4 = 900
    obs_6 = [0, 0, 0, 0, 0, 0, 0, 6]  # 6: not in the table
    got, seen = hand.lookup(np.array([obs_5, obs_900, obs_6], dtype=np.float32))
    assert got.dtype == torch.float32 and got.shape == (3, 4)
    assert seen.tolist() == [True, True, False]
    np.testing.assert_allclose(got[0].tolist(), authors_belief([3, 0, 1, 0]), rtol=1e-6)
    np.testing.assert_allclose(got[1].tolist(), authors_belief([50, 10, 0, 0]), rtol=1e-6)
    assert got[2].tolist() == [0.0] * 4
    assert hand.num_states == 2 and hand.num_actions == 4


def test_unseen_and_unkeyable_observations():
    hand = DemonstratorBelief(
        "driving",
        torch.tensor([0]),
        torch.tensor([[1, 2, 3]]),
        demonstrator_settings("driving", seed=0),
    )
    zero = [-2.0] * 6 + [0.0] * 5  # every entry at its lower bound -> key 0
    obs = torch.tensor(
        [
            zero,
            [-2.0] * 5 + [-1.5] + [0.0] * 5,  # a fraction
            [-2.0] * 5 + [9.0] + [0.0] * 5,  # beyond the bound 8
            [-2.0] * 5 + [float("nan")] + [0.0] * 5,
            [-1.0] * 6 + [0, 0, 1, 0, 0],
        ]
    )
    belief, seen = hand.lookup(obs)
    assert seen.tolist() == [True, False, False, False, False]
    assert (belief[1:] == 0).all()
    with pytest.raises(ValueError, match=r"obs: expected shape \[N, 11\]"):
        hand.lookup(torch.zeros(2, 8))
    with pytest.raises(ValueError, match="at least one counted action"):
        DemonstratorBelief("driving", torch.tensor([0]), torch.tensor([[0, 0, 0]]), {})
    with pytest.raises(ValueError, match="strictly increasing"):
        DemonstratorBelief("driving", torch.tensor([3, 1]), torch.ones(2, 3, dtype=torch.int64), {})


# ---------------------------------------------------------------------- FindMilk rule
def test_findmilk_weights_by_hand():
    obs = torch.tensor(
        [
            # (0,0), crying (2,2): up (0,1) d=3 -> 20*21/24 = 17.5; down/left wall (0,0) d=4
            # -> 20*20/24; right (1,0) d=3 -> 17.5
            START_OBS,
            # (7,6), crying (6,7): up = milk -> 20; down (7,5) d=3 -> 17.5; left (6,6) is a
            # sleeping cell -> 1; right wall (7,6) d=2 -> 20*22/24
            [7, 6, 7, 7, 6, 7, 6, 6],
            # (3,2), no crying baby left (0,0), nearest sleeping shown (5,4) although (3,3) is
            # an original sleeping cell: up (3,3) -> 1; down (3,1) d=4 -> 20*20/24;
            # left (2,2) d=4 -> 20*20/24; right (4,2) d=6 -> 20*18/24 = 15
            [3, 2, 7, 7, 0, 0, 5, 4],
        ],
        dtype=torch.float32,
    )
    got = findmilk_weights(obs)
    assert got.dtype == torch.float64
    np.testing.assert_allclose(got[0].tolist(), [17.5, 50 / 3, 50 / 3, 17.5])
    np.testing.assert_allclose(got[1].tolist(), [20, 17.5, 1, 55 / 3])
    np.testing.assert_allclose(got[2].tolist(), [1, 50 / 3, 50 / 3, 15])


def test_findmilk_start_action_frequencies():
    # every visit of the start state draws from [17.5, 50/3, 50/3, 17.5] / (205/3)
    table = play_findmilk(seed=11, episodes=400)
    start_key = sum(v * 8 ** (7 - i) for i, v in enumerate(START_OBS))  # radix 8
    row = int(torch.searchsorted(table.states, torch.tensor(start_key)))
    assert int(table.states[row]) == start_key
    counts = table.counts[row].tolist()
    n = sum(counts)
    assert n >= 400  # every episode starts there
    expected = [17.5 * 3 / 205, 50 / 205, 50 / 205, 17.5 * 3 / 205]
    for got, p in zip(counts, expected, strict=True):
        assert abs(got / n - p) < 4.5 * math.sqrt(p * (1 - p) / n)


def reference_findmilk(seed: int, episode: int) -> Counter:
    """One episode of ``human_policy_milk.py`` on our task, fed our demonstrator's draws."""
    sleep_positions = [(1, 1), (3, 3), (4, 0), (5, 4), (5, 5), (6, 6)]
    env = FindMilk(1, seed=task_seed(seed, episode))
    state = env.reset()[0].tolist()
    u_all = uniforms(episode_streams(seed, episode, 1, torch.device("cpu")), 0, 300)[0].tolist()
    trajectory: Counter = Counter()
    for t in range(300):
        x, y = state[0], state[1]
        probs = []
        for a in range(4):
            nx, ny = x + (a == 3) - (a == 2), y + (a == 0) - (a == 1)
            nx, ny = min(max(nx, 0), 7), min(max(ny, 0), 7)
            d_cry = abs(nx - state[4]) + abs(ny - state[5])
            if (nx, ny) in sleep_positions:
                probs.append(1)
            elif abs(nx - state[2]) + abs(ny - state[3]) == 0:
                probs.append(20)
            elif d_cry < 24:
                probs.append((24 - d_cry) / 24 * 20)
            else:
                probs.append(5)
        cdf = np.cumsum(probs)
        action = int(np.searchsorted(cdf, u_all[t] * cdf[-1], side="right"))
        trajectory[(tuple(state), action)] += 1
        obs, _, terminated, truncated, _ = env.step(torch.tensor([action]))
        if bool(terminated[0] or truncated[0]):
            break
        state = obs[0].tolist()
    return trajectory


def as_counter(table: DemonstratorBelief) -> Counter:
    """``(observation tuple, action) -> count`` of a table (decoding the keys by hand)."""
    bounds = observation_bounds(table.task_name)
    out: Counter = Counter()
    for key, row in zip(table.states.tolist(), table.counts.tolist(), strict=True):
        digits = []
        for lo, hi in reversed(bounds):
            key, d = divmod(key, hi - lo + 1)
            digits.append(float(d + lo))
        state = tuple(reversed(digits))
        for a, c in enumerate(row):
            if c:
                out[(state, a)] = c
    return out


def test_findmilk_matches_the_authors_loop():
    table = play_findmilk(seed=5, episodes=6, batch_size=4)
    expected: Counter = Counter()
    for e in range(6):
        expected.update(reference_findmilk(5, e))
    assert as_counter(table) == expected
    assert int(table.counts.sum()) == sum(expected.values())


# ---------------------------------------------------------------------- Driving Q-learner
def test_sarsa_update_by_hand():
    # Q(s0,a0) = 0.5, r = 0.5, Q(s1,a1) = -1: 0.5 + 0.1 * (0.5 - 0.99 - 0.5) = 0.401
    q = sarsa_update(0.5, 0.5, -1.0)
    assert q == pytest.approx(0.401)
    # then the episode ends with r = 20: 0.401 + 0.1 * (20 - 0.401) = 2.3609
    assert sarsa_update(q, 20.0) == pytest.approx(2.3609)
    # the same pair again: Q = 1, r = 0, Q' = 1 -> 1 + 0.1 * (0.99 - 1) = 0.999
    assert sarsa_update(1.0, 0.0, 1.0) == pytest.approx(0.999)
    got = sarsa_update(torch.tensor([0.5, 1.0]), torch.tensor([0.5, 0.0]), torch.tensor([-1, 1.0]))
    np.testing.assert_allclose(got.tolist(), [0.401, 0.999])


def test_human_reward_from_the_step_info():
    task = Driving(2, seed=0)
    task.reset()
    task.place("grandma", 2, 2)  # in the current lane, reached this step (2 - 3 <= 0)
    task.place("car", 3, 1)  # in the lane to the right, reached this step
    actions = torch.tensor([0, 1])
    _, _, _, _, info = task.step(actions)
    # straight: rescue only, +20 + 0.5; right: rescue (old lane) and collision (new lane)
    assert driving_human_reward(info, actions).tolist() == [20.5, 19.0]


def reference_driving(seed: int, episode: int, steps: int) -> Counter:
    """One episode of ``human_policy_drive.py`` on our task, fed our demonstrator's draws."""
    env = Driving(1, seed=task_seed(seed, episode), max_steps=steps)
    state = tuple(env.reset()[0].tolist())
    u_all = uniforms(episode_streams(seed, episode, 1, torch.device("cpu")), 0, 5 * steps)
    u_all = u_all[0].tolist()
    q: dict = {}
    trajectory: Counter = Counter()
    prev_pair = prev_reward = None
    for t in range(steps):
        u = u_all[5 * t : 5 * t + 5]
        if (state, 0) not in q:  # three standard normals by Box-Muller
            r0, r1 = math.sqrt(-2 * math.log1p(-u[0])), math.sqrt(-2 * math.log1p(-u[1]))
            normals = [r0 * math.cos(2 * math.pi * u[2]), r1 * math.cos(2 * math.pi * u[3])]
            normals.append(r0 * math.sin(2 * math.pi * u[2]))
            for a in range(3):
                q[(state, a)] = normals[a]
        probs = [math.e ** (q[(state, a)] / 0.7) for a in range(3)]
        cdf = np.cumsum(probs)
        action = int(np.searchsorted(cdf, u[4] * cdf[-1], side="right"))
        trajectory[(state, action)] += 1
        if prev_pair is not None:
            q[prev_pair] = q[prev_pair] + 0.1 * (
                prev_reward + 0.99 * q[(state, action)] - q[prev_pair]
            )
        obs, _, _, _, info = env.step(torch.tensor([action]))
        prev_pair = (state, action)
        prev_reward = (
            20 * int(info["rescues"][0]) - int(info["collisions"][0]) + 0.5 * (action == 0)
        )
        state = tuple(obs[0].tolist())
    return trajectory


def test_driving_matches_the_authors_loop():
    table = play_driving(seed=2, episodes=5, count_from=2, max_steps=300, batch_size=2)
    expected: Counter = Counter()
    for e in (2, 3, 4):
        expected.update(reference_driving(2, e, 300))
    assert as_counter(table) == expected
    assert int(table.counts.sum()) == 3 * 300
    # observations do repeat within an episode, so the per-episode table is exercised
    assert table.num_states < 3 * 300


def test_driving_counts_from_episode_601():
    table = demonstrator_belief("driving", seed=0, episodes=604)
    assert int(table.counts.sum()) == (604 - 601) * 300  # episodes 601, 602, 603
    assert table.settings["count_from"] == 601
    only_last = play_driving(seed=0, episodes=604, count_from=603)
    assert as_counter(only_last) == +(
        as_counter(table) - as_counter(play_driving(seed=0, episodes=603, count_from=601))
    )
    with pytest.raises(ValueError, match="count_from: expected less than episodes"):
        demonstrator_belief("driving", seed=0, episodes=601)


# ---------------------------------------------------------------------- determinism
def test_seeded_and_independent_of_batch_size():
    a = play_findmilk(seed=7, episodes=20, batch_size=20)
    b = play_findmilk(seed=7, episodes=20, batch_size=13)
    c = play_findmilk(seed=8, episodes=20)
    assert torch.equal(a.states, b.states) and torch.equal(a.counts, b.counts)
    assert not (a.states.shape == c.states.shape and torch.equal(a.counts, c.counts))
    d1 = play_driving(seed=4, episodes=4, count_from=0, batch_size=4)
    d2 = play_driving(seed=4, episodes=4, count_from=0, batch_size=3)
    assert torch.equal(d1.states, d2.states) and torch.equal(d1.counts, d2.counts)
    # neighbouring seeds share no episode (episode 1 of seed 4 is not episode 0 of seed 5)
    e1 = play_driving(seed=4, episodes=2, count_from=1)
    e0 = play_driving(seed=5, episodes=1, count_from=0)
    assert as_counter(e1) != as_counter(e0)
    with pytest.raises(ValueError, match="seed: expected a non-negative integer"):
        play_findmilk(seed=-1)


# ---------------------------------------------------------------------- save / load / cache
def test_save_load_round_trip(tmp_path):
    table = play_findmilk(seed=1, episodes=5)
    path = table.save(tmp_path / "sub" / "t.npz")
    with np.load(path, allow_pickle=False) as data:  # no pickle inside
        assert sorted(data.files) == ["counts", "settings", "states", "task"]
    back = DemonstratorBelief.load(path)
    assert back.task_name == "findmilk"
    assert torch.equal(back.states, table.states) and torch.equal(back.counts, table.counts)
    assert back.settings == table.settings
    assert back.settings["seed"] == 1 and back.settings["episodes"] == 5
    assert back.settings["count_from"] == 0
    DemonstratorBelief.load(path, expect={"seed": 1, "episodes": 5})
    with pytest.raises(DemonstratorCacheError, match=r"seed: file 1, wanted 2"):
        DemonstratorBelief.load(path, expect={"seed": 2})
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(DemonstratorCacheError, match=r"bad\.npz: not a readable"):
        DemonstratorBelief.load(bad)


def test_cache_is_reused_and_rebuilt_when_settings_differ(tmp_path):
    first = demonstrator_belief("findmilk", seed=3, episodes=8, cache_dir=tmp_path)
    path = cache_path(tmp_path, "findmilk", seed=3, episodes=8)
    assert path.is_file() and path.name == "human_demonstrator_findmilk_seed3_episodes8.npz"
    # a cache hit returns the file's table: plant other counts with the same settings
    planted = DemonstratorBelief(
        "findmilk", torch.tensor([1]), torch.tensor([[1, 0, 0, 0]]), first.settings
    )
    planted.save(path)
    assert demonstrator_belief("findmilk", seed=3, episodes=8, cache_dir=tmp_path).num_states == 1
    # a file made with another seed at that path is rebuilt and overwritten
    stale = dict(first.settings, seed=99)
    DemonstratorBelief("findmilk", torch.tensor([1]), torch.tensor([[1, 0, 0, 0]]), stale).save(
        path
    )
    again = demonstrator_belief("findmilk", seed=3, episodes=8, cache_dir=tmp_path)
    assert torch.equal(again.counts, first.counts) and again.settings["seed"] == 3
    assert DemonstratorBelief.load(path).settings["seed"] == 3
    path.write_bytes(b"garbage")
    with pytest.raises(DemonstratorCacheError, match="delete it"):
        demonstrator_belief("findmilk", seed=3, episodes=8, cache_dir=tmp_path)


# ---------------------------------------------------------------------- benchmark
def test_bench_demonstrators_runs(tmp_path, capsys):
    import amuled_ma.bench.demonstrators as bench

    out = tmp_path / "demo.json"
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    argv = ["--findmilk-episodes", "5", "--driving-episodes", "603", "--json", str(out)]
    assert bench.main(parser.parse_args(argv)) == 0
    text = capsys.readouterr().out
    assert "authors" in text and "1,120" in text and "12,270" in text
    figures = json.loads(out.read_text())
    assert figures["driving"]["episodes_played"] == 2  # episodes 601 and 602
    assert figures["driving"]["pairs_counted"] == 2 * 300
    assert figures["findmilk"]["states"] > 0
