"""Differential tests: the vectorised cores against plain-Python rule books.

The rule books below are written from docs/tasks.md with lists and sets (the way the
authors' code keeps its state); they receive the same random numbers as the cores (the
per-copy streams of :mod:`amuled_ma.tasks.rng`), so every observation and reward must agree.
"""

from __future__ import annotations

import numpy as np
import torch

from amuled_ma.tasks import rng as streams
from amuled_ma.tasks.driving import Driving
from amuled_ma.tasks.findmilk import CRYING, SLEEPING, FindMilk


class DrivingBook:
    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.lane = 2
        self.cars: dict[int, list[int]] = {lane: [] for lane in range(5)}
        self.gms: dict[int, list[int]] = {lane: [] for lane in range(5)}

    def obs(self) -> list[float]:
        out = []
        for q in (self.lane, self.lane - 1, self.lane + 1):
            for objs in (self.cars, self.gms):
                if not 0 <= q < 5:
                    out.append(-2.0)
                else:
                    out.append(float(min(objs[q])) if objs[q] else -1.0)
        return out + [float(i == self.lane) for i in range(5)]

    def step(self, action: int, car_lane: int | None, gm_lane: int | None):
        target = min(max(self.lane + (0, 1, -1)[action], 0), 4)
        self.cars = {k: [d - 1 for d in v] for k, v in self.cars.items()}
        self.gms = {k: [d - 3 for d in v] for k, v in self.gms.items()}
        lanes = {self.lane, target}
        collisions = sum(d <= 0 for q in lanes for d in self.cars[q])
        rescues = sum(d <= 0 for q in lanes for d in self.gms[q])
        self.cars = {k: [d for d in v if d > 0] for k, v in self.cars.items()}
        self.gms = {k: [d for d in v if d > 0] for k, v in self.gms.items()}
        if car_lane is not None:
            self.cars[car_lane].append(8)
        if gm_lane is not None:
            self.gms[gm_lane].append(8)
        r_env = -20 * collisions + 0.5 * (action == 0)
        r_shaping = 400 * rescues + 20 * (target == self.lane)
        self.lane = target
        return r_env, r_shaping, collisions, rescues


def test_driving_matches_the_rule_book():
    n, steps, seed, coef = 12, 420, 77, 0.5
    core = Driving(n, seed=seed, shaping_coef=coef)
    obs = core.reset()
    keys = streams.copy_keys(seed, n, torch.device("cpu"))
    t_car, t_gm = streams.threshold32(0.16), streams.threshold32(0.09)
    books = [DrivingBook() for _ in range(n)]
    rng = np.random.default_rng(3)
    for t in range(steps):
        z = streams.draw(keys, torch.full((n,), t, dtype=torch.int64))
        u_car = (z & streams.MASK32).tolist()
        u_gm = streams.shift_right(z, 32).tolist()
        actions = rng.integers(0, 3, n)
        obs, reward, term, trunc, info = core.step(torch.as_tensor(actions))
        for i, book in enumerate(books):
            car = u_car[i] * 5 // t_car if u_car[i] < t_car else None
            gm = u_gm[i] * 5 // t_gm if u_gm[i] < t_gm else None
            r_env, r_shaping, col, res = book.step(int(actions[i]), car, gm)
            assert info["final_obs"][i].tolist() == book.obs(), (t, i)
            assert (info["r_env"][i].item(), info["r_shaping"][i].item()) == (r_env, r_shaping)
            assert (info["collisions"][i].item(), info["rescues"][i].item()) == (col, res)
            assert reward[i].item() == r_env + coef * r_shaping
            assert trunc[i].item() == ((t + 1) % 300 == 0)
            assert not term[i].item()
            if trunc[i]:
                book.reset()
            assert obs[i].tolist() == book.obs()


class FindMilkBook:
    moves = ((0, 1), (0, -1), (-1, 0), (1, 0))

    def __init__(self) -> None:
        self.pos = (0, 0)
        self.crying = set(CRYING)
        self.sleeping = set(SLEEPING)

    @staticmethod
    def nearest(pos, babies) -> tuple[int, int]:
        if not babies:
            return (0, 0)
        return min(babies, key=lambda b: ((b[0] - pos[0]) ** 2 + (b[1] - pos[1]) ** 2, b))

    def obs(self) -> list[float]:
        cry = self.nearest(self.pos, self.crying)
        sleep = self.nearest(self.pos, self.sleeping)
        return [float(v) for v in (*self.pos, 7, 7, *cry, *sleep)]

    def step(self, action: int):
        dx, dy = self.moves[action]
        x, y = self.pos[0] + dx, self.pos[1] + dy
        if 0 <= x < 8 and 0 <= y < 8:
            self.pos = (x, y)
        pacified = self.pos in self.crying
        woken = self.pos in self.sleeping
        self.crying.discard(self.pos)
        self.sleeping.discard(self.pos)
        reached = self.pos == (7, 7)
        return (20.0 if reached else -1.0), float(pacified) - float(woken), reached


def test_findmilk_matches_the_rule_book():
    n, steps = 16, 600
    core = FindMilk(n, seed=0, shaping_coef=2.0, max_steps=60)
    core.reset()
    books = [FindMilkBook() for _ in range(n)]
    rng = np.random.default_rng(5)
    ends = {"terminated": 0, "truncated": 0}
    for t in range(steps):
        # a drift towards the milk so that episodes end both ways
        actions = np.where(rng.random(n) < 0.35, rng.choice([0, 3], n), rng.integers(0, 4, n))
        obs, reward, term, trunc, info = core.step(torch.as_tensor(actions))
        for i, book in enumerate(books):
            r_env, r_shaping, reached = book.step(int(actions[i]))
            assert info["final_obs"][i].tolist() == book.obs(), (t, i)
            assert (info["r_env"][i].item(), info["r_shaping"][i].item()) == (r_env, r_shaping)
            assert reward[i].item() == r_env + 2.0 * r_shaping
            assert term[i].item() == reached
            if term[i] or trunc[i]:
                books[i] = FindMilkBook()
                ends["terminated" if term[i] else "truncated"] += 1
            assert obs[i].tolist() == books[i].obs()
    assert ends["terminated"] > 10 and ends["truncated"] > 10, ends
