"""Driving and Rescuing: a car on a five-lane road avoids cars and rescues grandmas.

## Description

The toy model of Wu and Lin (2018) used by the AMULED paper. A road of 5 lanes
(``0..4``); the agent's car starts in lane 2. Other cars and grandmas appear at distance 8
ahead and approach: cars by 1 unit per step, grandmas by 3 units per step. One step:

1. the action picks the target lane (0 straight, 1 right = lane+1, 2 left = lane-1),
   clipped to ``0..4``;
2. every object's distance decreases by its speed;
3. hits: if the lane changes, objects at distance <= 0 in the current *and* the target
   lane count, otherwise those in the current lane only; a car hit is a collision, a
   grandma hit is a rescue; the agent is then in the target lane;
4. every object at distance <= 0 is removed, in every lane;
5. spawning: with probability 0.16 one car is added at distance 8 in a uniformly random
   lane, and independently with probability 0.09 one grandma likewise;
6. reward.

The episode lasts 300 steps (time limit, reported as truncation; it never terminates).

Implementation note: since at most one car and one grandma appear per step and every
object of a kind moves at the same speed, an object's distance is fixed by its age. The
state is therefore a ring of 8 car slots and 3 grandma slots per copy (slot = spawn step
modulo the lifetime), each holding the object's lane or "empty"; a car reaches distance
<= 0 exactly 8 steps after it appeared, a grandma 3 steps after (8 -> 5 -> 2 -> -1).

## Action Space

``Discrete(3)``: ``0`` straight, ``1`` right (lane+1), ``2`` left (lane-1). At the road's
edge the move is clipped (the lane does not change; the action is not "straight").

## Observation Space

``Box((11,), float32)``: ``[car_current, grandma_current, car_left, grandma_left, car_right,
grandma_right]`` then the one-hot lane (5 entries). Each distance entry is the distance to
the nearest object of that kind in that lane (1..8), -1 when the lane holds none, -2 when
the lane does not exist (left = lane-1, right = lane+1).

## Rewards

``r_env = -20 * collisions + 0.5 * [action == straight]``.
Handcrafted shaping ``r_shaping = 400 * rescues + 20 * [lane_t == lane_{t-1}]``.
The returned reward is ``r_env + c * r_shaping`` with ``c = shaping_coef``.

## Info

Per step (``[num_envs]`` tensors): ``r_env``, ``r_shaping``, ``collisions`` and ``rescues``
(int64, this step), ``lane_changes`` (bool, the lane changed), ``final_obs``; per episode
(``info["episode"]``, read where ``done``): ``return``, ``return_env``, ``return_shaping``,
``length``, ``collisions``, ``rescues`` (grandmas rescued), ``lane_changes``.

## Version History

- v0: first version, the rules of issue 3.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, ClassVar

import numpy as np
import torch

from amuled_ma.tasks import _rng
from amuled_ma.tasks.base import BatchedTask

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
_EMPTY = -10  # lane value of an empty slot
_FAR = 1000


class Driving(BatchedTask):
    """Driving and Rescuing, ``num_envs`` copies at once (rules in the module documentation).

    Args:
        num_envs: Number of copies.
        device: Torch device.
        seed: Base seed (copy ``i`` uses seed ``seed + i``).
        shaping_coef: Coefficient ``c >= 0`` of the shaping reward.
        max_steps: Episode length in steps (time limit).
        p_car: Probability that a car appears on a step (paper: 0.16).
        p_grandma: Probability that a grandma appears on a step (paper: 0.09).

    Raises:
        ValueError: An argument is out of range.

    """

    name: ClassVar[str] = "driving"
    gym_id: ClassVar[str] = "amuled/Driving-v0"
    action_names: ClassVar[tuple[str, ...]] = ("straight", "right", "left")
    obs_names: ClassVar[tuple[str, ...]] = (
        "car_current", "grandma_current", "car_left", "grandma_left", "car_right",
        "grandma_right", "lane_is_0", "lane_is_1", "lane_is_2", "lane_is_3", "lane_is_4",
    )  # fmt: skip
    obs_low: ClassVar[tuple[float, ...]] = (-2.0,) * 6 + (0.0,) * NUM_LANES
    obs_high: ClassVar[tuple[float, ...]] = (float(SPAWN_DISTANCE),) * 6 + (1.0,) * NUM_LANES
    metric_names: ClassVar[tuple[str, ...]] = ("collisions", "rescues", "lane_changes")
    num_lanes: ClassVar[int] = NUM_LANES

    def __init__(
        self,
        num_envs: int = 1,
        *,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        shaping_coef: float = 0.0,
        max_steps: int = 300,
        p_car: float = P_CAR,
        p_grandma: float = P_GRANDMA,
    ) -> None:
        super().__init__(
            num_envs,
            device=device,
            seed=seed,
            shaping_coef=shaping_coef,
            max_steps=max_steps,
            p_car=p_car,
            p_grandma=p_grandma,
        )

    def _init_task(self, p_car: float = P_CAR, p_grandma: float = P_GRANDMA) -> None:
        for label, p in (("p_car", p_car), ("p_grandma", p_grandma)):
            if not isinstance(p, numbers.Real) or isinstance(p, bool) or not 0.0 <= float(p) <= 1.0:
                raise ValueError(f"{label}: expected a probability in [0, 1], got {p!r}")
        self.p_car = float(p_car)
        self.p_grandma = float(p_grandma)
        self._t_car = _rng.threshold32(self.p_car)
        self._t_gm = _rng.threshold32(self.p_grandma)
        n, dev = self.num_envs, self.device
        self._tick = 0  # global step counter: selects the ring slots
        self._lane = torch.full((n,), START_LANE, dtype=torch.int64, device=dev)
        self._car = torch.full((n, _CAR_SLOTS), _EMPTY, dtype=torch.int64, device=dev)
        self._gm = torch.full((n, _GM_SLOTS), _EMPTY, dtype=torch.int64, device=dev)
        # target lane of (lane, action)
        target = [
            min(max(lane + d, 0), NUM_LANES - 1) for lane in range(NUM_LANES) for d in (0, 1, -1)
        ]
        self._target = torch.tensor(target, dtype=torch.int64, device=dev)
        # distance of the object in each slot, for each ring phase (tick modulo slot count)
        self._car_dist = self._ring_distances(_CAR_SLOTS, CAR_SPEED)
        self._gm_dist = self._ring_distances(_GM_SLOTS, GRANDMA_SPEED)
        self._onehot = torch.eye(NUM_LANES, dtype=torch.float32, device=dev)
        self._offsets = torch.tensor([0, -1, 1], dtype=torch.int64, device=dev)
        self._initial_obs = torch.tensor(
            [-1.0] * 6 + [float(i == START_LANE) for i in range(NUM_LANES)],
            dtype=torch.float32,
            device=dev,
        )

    def _ring_distances(self, slots: int, speed: int) -> torch.Tensor:
        """``[slots, slots]``: row ``phase``, column ``slot`` -> distance after the step.

        After global step ``g`` the object spawned on step ``g - k`` sits in slot
        ``(g - k) % slots`` at distance ``8 - speed * k``.
        """
        table = [
            [SPAWN_DISTANCE - speed * ((phase - s) % slots) for s in range(slots)]
            for phase in range(slots)
        ]
        return torch.tensor(table, dtype=torch.int64, device=self.device)

    # ------------------------------------------------------------------ rules
    def _advance(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        self._tick += 1
        car_slot = self._tick % _CAR_SLOTS  # holds the car now at distance 1 -> 0
        gm_slot = self._tick % _GM_SLOTS  # holds the grandma now at distance 2 -> -1
        lane = self._lane
        target = self._target[lane * 3 + actions]  # (1) target lane
        changed = target != lane
        # (2) + (3): the objects reaching distance <= 0 this step are the oldest ones
        car_lane = self._car[:, car_slot]
        gm_lane = self._gm[:, gm_slot]
        collisions = ((car_lane == lane) | (changed & (car_lane == target))).to(torch.int64)
        rescues = ((gm_lane == lane) | (changed & (gm_lane == target))).to(torch.int64)
        self._lane = target
        # (4) removal and (5) spawning: the new object takes the freed slot
        z = self._draw()
        u_car = z & _rng.MASK32
        u_gm = _rng._srl(z, 32)
        self._car[:, car_slot] = torch.where(
            u_car < self._t_car, (u_car * NUM_LANES) // max(self._t_car, 1), _EMPTY
        )
        self._gm[:, gm_slot] = torch.where(
            u_gm < self._t_gm, (u_gm * NUM_LANES) // max(self._t_gm, 1), _EMPTY
        )
        # (6) reward
        r_env = -20.0 * collisions + 0.5 * (actions == 0)
        r_shaping = 400.0 * rescues + 20.0 * ~changed
        events = {"collisions": collisions, "rescues": rescues, "lane_changes": changed}
        return (
            r_env.to(torch.float32),
            r_shaping.to(torch.float32),
            torch.zeros_like(changed),
            events,
        )

    def _reset_where(self, mask: torch.Tensor) -> None:
        self._lane = torch.where(mask, START_LANE, self._lane)
        self._car = torch.where(mask[:, None], _EMPTY, self._car)
        self._gm = torch.where(mask[:, None], _EMPTY, self._gm)

    def _lane_distances(
        self, ring: torch.Tensor, dist: torch.Tensor, lanes: torch.Tensor
    ) -> torch.Tensor:
        """Nearest distance per queried lane (``[N, 3]``), -1 none, -2 no such lane."""
        match = ring[:, None, :] == lanes[:, :, None]  # [N, 3, slots]
        d = torch.where(match, dist, _FAR).amin(2)
        d = torch.where(d == _FAR, -1, d)
        return torch.where((lanes < 0) | (lanes >= NUM_LANES), -2, d)

    def _observe(self) -> torch.Tensor:
        lanes = self._lane[:, None] + self._offsets  # current, left, right
        cars = self._lane_distances(self._car, self._car_dist[self._tick % _CAR_SLOTS], lanes)
        gms = self._lane_distances(self._gm, self._gm_dist[self._tick % _GM_SLOTS], lanes)
        dists = torch.stack([cars, gms], 2).reshape(self.num_envs, 6).to(torch.float32)
        return torch.cat([dists, self._onehot[self._lane]], 1)

    def _observe_after_reset(self, final_obs: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        return torch.where(done[:, None], self._initial_obs, final_obs)

    # ------------------------------------------------------------------ state access
    @property
    def lane(self) -> torch.Tensor:
        """Current lane of each copy (int64 ``[num_envs]``)."""
        return self._lane

    def place(self, kind: str, lane: int, distance: int, env_ids: Any = None) -> None:
        """Put an object on the road (for tests and hand-made states); updates ``obs``.

        Objects of one kind appear at most one per step, so each distance a kind can
        occupy holds at most one object: placing replaces what was there.

        Args:
            kind: ``"car"`` (distance 1..8) or ``"grandma"`` (distance 2, 5 or 8).
            lane: Lane 0..4.
            distance: Distance ahead, as it would appear in the observation.
            env_ids: Copies to change (``None``: all).

        Raises:
            ValueError: Unknown ``kind``, or ``lane`` / ``distance`` impossible.

        """
        if kind == "car":
            ring, slots, speed = self._car, _CAR_SLOTS, CAR_SPEED
        elif kind == "grandma":
            ring, slots, speed = self._gm, _GM_SLOTS, GRANDMA_SPEED
        else:
            raise ValueError(f"kind: expected 'car' or 'grandma', got {kind!r}")
        if not 0 <= int(lane) < NUM_LANES:
            raise ValueError(f"lane: expected 0..{NUM_LANES - 1}, got {lane!r}")
        age, rest = divmod(SPAWN_DISTANCE - int(distance), speed)
        if rest or not 0 <= age < slots:
            allowed = [SPAWN_DISTANCE - speed * k for k in range(slots)]
            raise ValueError(f"distance: a {kind} can only be at {allowed}, got {distance!r}")
        ids = self._env_ids(env_ids)
        ring[ids, (self._tick - age) % slots] = int(lane)
        self._obs = self._observe()

    def clear_road(self, env_ids: Any = None) -> None:
        """Remove every car and grandma from the selected copies; updates ``obs``."""
        ids = self._env_ids(env_ids)
        self._car[ids] = _EMPTY
        self._gm[ids] = _EMPTY
        self._obs = self._observe()

    def set_lane(self, lane: int, env_ids: Any = None) -> None:
        """Move the agent's car to ``lane`` in the selected copies; updates ``obs``."""
        if not 0 <= int(lane) < NUM_LANES:
            raise ValueError(f"lane: expected 0..{NUM_LANES - 1}, got {lane!r}")
        self._lane[self._env_ids(env_ids)] = int(lane)
        self._obs = self._observe()

    def objects(self, env_id: int = 0) -> dict[str, list[tuple[int, int]]]:
        """Return ``{"car": [(lane, distance), ...], "grandma": [...]}`` of one copy."""
        env_id = self._env_id(env_id)
        out: dict[str, list[tuple[int, int]]] = {}
        for kind, ring, table, slots in (
            ("car", self._car, self._car_dist, _CAR_SLOTS),
            ("grandma", self._gm, self._gm_dist, _GM_SLOTS),
        ):
            dist = table[self._tick % slots].tolist()
            out[kind] = sorted(
                (lane, d) for lane, d in zip(ring[env_id].tolist(), dist, strict=True) if lane >= 0
            )
        return out

    # ------------------------------------------------------------------ prompts
    @classmethod
    def prompt_variables_from_obs(cls, obs: np.ndarray, **extra: Any) -> dict[str, Any]:
        """Return the Driving prompt variables of one observation.

        Args:
            obs: The 11 observation floats.
            **extra: Further variables, copied into the result.

        Returns:
            ``lane`` (int) and the six distances as ints (``car_current``, ...,
            ``grandma_right``), with -1 = none and -2 = no such lane.

        Raises:
            ValueError: ``obs`` is not 11 numbers or its lane one-hot is invalid.

        """
        values = np.asarray(obs, dtype=np.float64).reshape(-1)
        if values.shape != (len(cls.obs_names),):
            raise ValueError(
                f"obs: expected {len(cls.obs_names)} numbers, got shape {np.shape(obs)}"
            )
        onehot = values[6:]
        if not (np.isin(onehot, (0.0, 1.0)).all() and onehot.sum() == 1):
            raise ValueError(
                f"obs: the last 5 entries must be a one-hot lane, got {onehot.tolist()}"
            )
        out: dict[str, Any] = {"lane": int(np.argmax(onehot))}
        out.update((k, round(v)) for k, v in zip(cls.obs_names[:6], values[:6], strict=True))
        out.update(extra)
        return out

    # ------------------------------------------------------------------ rendering
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
        """Return the road as text: distance 8 on top, the agent ``A`` at distance 0.

        ``c`` car, ``g`` grandma, ``*`` both at the same place, ``.`` empty.
        """
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
        height = SPAWN_DISTANCE + 1
        img = np.full((height * cell, NUM_LANES * cell, 3), 110, dtype=np.uint8)
        pad = max(1, cell // 8)
        for d in range(height):
            r = SPAWN_DISTANCE - d
            for lane in range(NUM_LANES):
                ch = rows[d][lane]
                if ch != ".":
                    img[r * cell + pad : (r + 1) * cell - pad,
                        lane * cell + pad : (lane + 1) * cell - pad] = colours[ch]  # fmt: skip
        img[:, ::cell] = (240, 240, 240)
        return img
