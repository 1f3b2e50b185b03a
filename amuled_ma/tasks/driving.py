"""Driving and Rescuing (Wu and Lin 2018): a car on a five-lane road avoids cars, rescues grandmas.

Rules, spaces, rewards, the bit-packed road and the ``info`` keys: docs/tasks.md, "Driving and
Rescuing".
"""

from __future__ import annotations

import math
import numbers
from typing import Any, ClassVar

import numpy as np
import torch

from amuled_ma.tasks import rng
from amuled_ma.tasks.base import BatchedTask, check_int, paint_cells

__all__ = ["Driving"]

NUM_LANES = 5
START_LANE = 2
SPAWN_DISTANCE = 8
CAR_SPEED = 1
GRANDMA_SPEED = 3
P_CAR = 0.16
P_GRANDMA = 0.09
_CAR_SLOTS = math.ceil(SPAWN_DISTANCE / CAR_SPEED)  # 8 steps alive
_GM_SLOTS = math.ceil(SPAWN_DISTANCE / GRANDMA_SPEED)  # 3 steps alive
_CAR_W = _CAR_SLOTS + 1  # bits per lane group: distance <= 0 (bit 0) and 1..8
_GM_W = _GM_SLOTS + 1  # bits per lane group: distance <= 0 (bit 0), 2, 5, 8
#: Object kind -> (bits per lane group, the distance of each slot 1..slots: ``[1, 2, ...]``).
_KINDS = {
    kind: (slots + 1, [SPAWN_DISTANCE - speed * (slots - k) for k in range(1, slots + 1)])
    for kind, slots, speed in (
        ("car", _CAR_SLOTS, CAR_SPEED),
        ("grandma", _GM_SLOTS, GRANDMA_SPEED),
    )
}


class Driving(BatchedTask):
    """Driving and Rescuing, ``num_envs`` copies; ``p_car``, ``p_grandma``: appearance per step."""

    name: ClassVar[str] = "driving"
    gym_id: ClassVar[str] = "amuled/Driving-v0"
    action_names: ClassVar[tuple[str, ...]] = ("straight", "right", "left")
    obs_names: ClassVar[tuple[str, ...]] = (
        "car_current", "grandma_current", "car_left", "grandma_left", "car_right",
        "grandma_right", "lane_is_0", "lane_is_1", "lane_is_2", "lane_is_3", "lane_is_4",
    )  # fmt: skip
    obs_low: ClassVar[tuple[float, ...]] = (-2.0,) * 6 + (0.0,) * NUM_LANES
    obs_high: ClassVar[tuple[float, ...]] = (float(SPAWN_DISTANCE),) * 6 + (1.0,) * NUM_LANES
    metric_names: ClassVar[tuple[str, ...]] = (
        "collisions", "rescues", "lane_changes", "non_straight_steps",
    )  # fmt: skip
    num_lanes: ClassVar[int] = NUM_LANES
    human_feedback: ClassVar[bool] = True

    def _init_task(self, p_car: float = P_CAR, p_grandma: float = P_GRANDMA) -> None:
        for label, p in (("p_car", p_car), ("p_grandma", p_grandma)):
            if not isinstance(p, numbers.Real) or isinstance(p, bool) or not 0.0 <= float(p) <= 1.0:
                raise ValueError(f"{label}: expected a probability in [0, 1], got {p!r}")
        self.p_car = float(p_car)
        self.p_grandma = float(p_grandma)
        self._t_car = rng.threshold32(self.p_car)
        self._t_gm = rng.threshold32(self.p_grandma)
        n, dev = self.num_envs, self.device
        i64 = torch.int64
        self._lane = torch.full((n,), START_LANE, dtype=i64, device=dev)
        self._cars = torch.zeros(n, dtype=i64, device=dev)  # bit (lane+1)*9 + d: car at d
        self._gms = torch.zeros(n, dtype=i64, device=dev)  # bit (lane+1)*4 + k: grandma
        # per (lane, action): target lane, straight bonus and the "same lane" shaping term
        target, bonus, same = [], [], []
        for lane in range(NUM_LANES):
            for action, d in enumerate((0, 1, -1)):
                t = min(max(lane + d, 0), NUM_LANES - 1)
                target.append(t)
                bonus.append(0.5 if action == 0 else 0.0)
                same.append(20.0 if t == lane else 0.0)
        self._target = torch.tensor(target, dtype=i64, device=dev)
        self._straight_bonus = torch.tensor(bonus, dtype=torch.float32, device=dev)
        self._same_lane = torch.tensor(same, dtype=torch.float32, device=dev)
        lanes = range(NUM_LANES)
        car, gm = (
            [
                torch.tensor(values, dtype=i64, device=dev)
                for values in (
                    # hit masks per (lane, action): bit 0 of the current and the target lane group
                    [1 << (i // 3 + 1) * w | 1 << (t + 1) * w for i, t in enumerate(target)],
                    # observed lanes current, left, right -> group shifts (pad groups 0 and 6)
                    [[(ln + 1) * w, ln * w, (ln + 2) * w] for ln in lanes],
                    1 | 1 << (NUM_LANES + 1) * w,  # the pad groups
                    ~sum(1 << (ln + 1) * w for ln in lanes),  # keeps all but distance <= 0
                    [1 << ((ln + 1) * w + slots) for ln in lanes] + [0],  # spawn bit; 5: none
                )
            ]
            for w, slots in ((_CAR_W, _CAR_SLOTS), (_GM_W, _GM_SLOTS))
        )
        self._hit_car, self._obs_car_shift, self._pad_car, self._keep_car, self._spawn_car = car
        self._hit_gm, self._obs_gm_shift, self._pad_gm, self._keep_gm, self._spawn_gm = gm
        self._lane_table = self._observation_table()
        self._onehot = torch.eye(NUM_LANES, dtype=torch.float32, device=dev)
        self._initial_obs = torch.tensor(
            [-1.0] * 6 + [float(i == START_LANE) for i in range(NUM_LANES)],
            dtype=torch.float32,
            device=dev,
        )

    @staticmethod
    def _group_distance(group: int, kind: str) -> int:
        """Observed distance of one lane group: nearest object, -1 none, -2 no lane."""
        distances = _KINDS[kind][1]
        found = (d for k, d in enumerate(distances, 1) if group >> k & 1)
        return -2 if group & 1 else next(found, -1)

    def _observation_table(self) -> torch.Tensor:
        """``[512 * 16, 2]``: (car group, grandma group) of a lane -> observed distances."""
        rows = []
        for g_car in range(1 << _CAR_W):
            d_car = self._group_distance(g_car, "car")
            for g_gm in range(1 << _GM_W):
                rows.append((d_car, self._group_distance(g_gm, "grandma")))
        return torch.tensor(rows, dtype=torch.float32, device=self.device)

    def _advance(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        idx = self._lane * 3 + actions
        target = self._target.index_select(0, idx)  # (1) target lane
        cars = self._cars >> 1  # (2) every object advances (one bit per step)
        gms = self._gms >> 1
        # (3) hits: objects now at distance <= 0 (bit 0 of a lane group) in the current or
        # the target lane (the same lane when it does not change); at most one object of a
        # kind reaches distance <= 0 per step, since at most one appears per step
        collisions = ((cars & self._hit_car.index_select(0, idx)) != 0).to(torch.int64)
        rescues = ((gms & self._hit_gm.index_select(0, idx)) != 0).to(torch.int64)
        changed = target != self._lane
        self._lane = target
        # (4) removal of everything at distance <= 0, (5) spawning at distance 8
        cars = cars & self._keep_car
        gms = gms & self._keep_gm
        z = self._draw()
        if self._t_car:
            u = z & rng.MASK32
            lane_car = ((u * NUM_LANES) // self._t_car).clamp_(max=NUM_LANES)
            cars = cars | self._spawn_car.index_select(0, lane_car)
        if self._t_gm:
            u = rng.shift_right(z, 32)
            lane_gm = ((u * NUM_LANES) // self._t_gm).clamp_(max=NUM_LANES)
            gms = gms | self._spawn_gm.index_select(0, lane_gm)
        self._cars = cars
        self._gms = gms
        # (6) reward
        r_env = collisions * -20.0 + self._straight_bonus.index_select(0, idx)
        r_shaping = rescues * 400.0 + self._same_lane.index_select(0, idx)
        events = {
            "collisions": collisions,
            "rescues": rescues,
            "lane_changes": changed,
            "non_straight_steps": actions != 0,  # action 0 is straight
        }
        terminated = torch.zeros_like(changed)  # the road never ends early
        return r_env, r_shaping, terminated, events

    def _reset_where(self, mask: torch.Tensor) -> None:
        self._lane = torch.where(mask, START_LANE, self._lane)
        self._cars = torch.where(mask, 0, self._cars)
        self._gms = torch.where(mask, 0, self._gms)

    def _observe(self) -> torch.Tensor:
        cars = (self._cars | self._pad_car)[:, None]
        gms = (self._gms | self._pad_gm)[:, None]
        g_car = (cars >> self._obs_car_shift.index_select(0, self._lane)) & ((1 << _CAR_W) - 1)
        g_gm = (gms >> self._obs_gm_shift.index_select(0, self._lane)) & ((1 << _GM_W) - 1)
        key = (g_car << _GM_W) | g_gm  # [N, 3]: current, left, right
        dists = self._lane_table.index_select(0, key.reshape(-1)).reshape(self.num_envs, 6)
        return torch.cat([dists, self._onehot.index_select(0, self._lane)], 1)

    @property
    def lane(self) -> torch.Tensor:
        """Current lane of each copy (int64 ``[num_envs]``)."""
        return self._lane

    def _bit(self, kind: str, lane: int, distance: int) -> tuple[int, int]:
        """Return the bit of an object and the bits of that distance in every lane."""
        if kind not in _KINDS:
            raise ValueError(f"kind: expected 'car' or 'grandma', got {kind!r}")
        width, allowed = _KINDS[kind]
        lane = check_int(lane, "lane", 0, NUM_LANES - 1)
        if distance not in allowed:
            raise ValueError(f"distance: a {kind} can only be at {allowed}, got {distance!r}")
        k = allowed.index(distance) + 1
        row = sum(1 << ((ln + 1) * width + k) for ln in range(NUM_LANES))
        return 1 << ((int(lane) + 1) * width + k), row

    def place(self, kind: str, lane: int, distance: int, env_ids: object = None) -> None:
        """Put a ``"car"`` (distance 1..8) or ``"grandma"`` (2, 5, 8) on the road; updates ``obs``.

        ``env_ids`` None: all. Two objects of a kind never share a distance (the step relies on it).

        Raises:
            ValueError: Unknown ``kind``; ``lane`` or ``distance`` impossible; another
                object of that kind already at that distance in another lane.
        """
        bit, row = self._bit(kind, lane, distance)
        ids = self._env_ids(env_ids)
        road = self._cars if kind == "car" else self._gms
        if bool(((road[ids] & (row & ~bit)) != 0).any()):
            raise ValueError(
                f"distance: another {kind} is already at distance {distance} in another lane "
                "(the rules let at most one appear per step)"
            )
        road[ids] |= bit
        self._obs = self._observe()

    def clear_road(self, env_ids: object = None) -> None:
        """Remove every car and grandma from the selected copies; updates ``obs``."""
        ids = self._env_ids(env_ids)
        self._cars[ids] = 0
        self._gms[ids] = 0
        self._obs = self._observe()

    def set_lane(self, lane: int, env_ids: object = None) -> None:
        """Move the agent's car to ``lane`` in the selected copies; updates ``obs``."""
        self._lane[self._env_ids(env_ids)] = check_int(lane, "lane", 0, NUM_LANES - 1)
        self._obs = self._observe()

    def road(self) -> dict[str, torch.Tensor]:
        """Return ``{"car", "grandma"}`` occupancy, bool ``[num_envs, 5, 9]`` (lane, distance)."""
        out = {}
        for kind, bits in (("car", self._cars), ("grandma", self._gms)):
            width, distances = _KINDS[kind]
            grid = torch.zeros(
                self.num_envs, NUM_LANES, SPAWN_DISTANCE + 1, dtype=torch.bool, device=self.device
            )
            for k, d in enumerate(distances, 1):
                shifts = torch.arange(1, NUM_LANES + 1, device=self.device) * width + k
                grid[:, :, d] = (bits[:, None] >> shifts) & 1 == 1
            out[kind] = grid
        return out

    def objects(self, env_id: int = 0) -> dict[str, list[tuple[int, int]]]:
        """Return ``{"car": [(lane, distance), ...], "grandma": [...]}`` of one copy."""
        env_id = self._env_id(env_id)
        out: dict[str, list[tuple[int, int]]] = {}
        for kind, bits in (("car", int(self._cars[env_id])), ("grandma", int(self._gms[env_id]))):
            width, distances = _KINDS[kind]
            out[kind] = [
                (lane, d)
                for lane in range(NUM_LANES)
                for k, d in enumerate(distances, 1)
                if bits >> ((lane + 1) * width + k) & 1
            ]
        return out

    @classmethod
    def prompt_variables_from_obs(cls, obs: np.ndarray, **extra: Any) -> dict[str, Any]:
        """Return ``lane``, the six distances (-1 none, -2 no lane) as ints, and ``extra``.

        Raises:
            ValueError: ``obs`` is not 11 numbers or its lane one-hot is invalid.
        """
        values = cls._obs_values(obs)
        onehot = values[6:]
        if not (np.isin(onehot, (0.0, 1.0)).all() and onehot.sum() == 1):
            raise ValueError(
                f"obs: the last 5 entries must be a one-hot lane, got {onehot.tolist()}"
            )
        out: dict[str, Any] = {"lane": int(np.argmax(onehot))}
        out.update((k, round(v)) for k, v in zip(cls.obs_names[:6], values[:6], strict=True))
        out.update(extra)
        return out

    def _road_chars(self, env_id: int) -> list[list[str]]:
        rows = [["." for _ in range(NUM_LANES)] for _ in range(SPAWN_DISTANCE + 1)]  # [dist][lane]
        objs = self.objects(env_id)
        for lane, d in objs["car"]:
            rows[d][lane] = "c"
        for lane, d in objs["grandma"]:
            rows[d][lane] = "*" if rows[d][lane] == "c" else "g"
        rows[0][int(self._lane[env_id])] = "A"
        return rows

    def render_ansi(self, env_id: int = 0) -> str:
        """The road, distance 8 on top: ``A`` agent, ``c`` car, ``g`` grandma, ``*`` both."""
        env_id = self._env_id(env_id)
        rows = self._road_chars(env_id)
        lines = [
            f"Driving step {int(self._t[env_id])}/{self.max_steps}  lane {int(self._lane[env_id])}"
        ]
        lines += [f"{d} |" + " ".join(rows[d]) + "|" for d in range(SPAWN_DISTANCE, -1, -1)]
        lines.append("   " + " ".join(str(i) for i in range(NUM_LANES)))
        return "\n".join(lines) + "\n"

    def render_rgb(self, env_id: int = 0, cell: int = 32) -> np.ndarray:
        """Return an RGB image (uint8 ``[9*cell, 5*cell, 3]``), distance 8 at the top row."""
        env_id = self._env_id(env_id)
        colours = {
            "c": (220, 60, 60),
            "g": (60, 170, 80),
            "*": (230, 160, 40),
            "A": (40, 40, 40),
        }
        rows = self._road_chars(env_id)
        img = paint_cells(rows[::-1], colours, cell, background=110)  # distance 8 on top
        img[:, ::cell] = (240, 240, 240)
        return img
