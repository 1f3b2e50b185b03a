"""FindMilk: a robot looks for milk in a room of crying and sleeping babies.

Rules, spaces, rewards, the tie-break and the ``info`` keys: docs/tasks.md, "FindMilk".
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from amuled_ma.tasks.base import BatchedTask, paint_cells

__all__ = ["CRYING", "LAYOUTS", "MILK", "SIZE", "SLEEPING", "START", "TIE_BREAKS", "FindMilk"]

SIZE = 8
START = (0, 0)
MILK = (7, 7)
SLEEPING = ((1, 1), (3, 3), (4, 0), (5, 4), (5, 5), (6, 6))
CRYING = ((2, 2), (2, 3), (4, 4), (5, 6), (6, 7))
LAYOUTS = ("paper", "random")
#: How a tie for the nearest baby is broken: first in ``(x, y)`` order, or at random.
TIE_BREAKS = ("first", "random")

_MOVES = ((0, 1), (0, -1), (-1, 0), (1, 0))  # (dx, dy) of up, down, left, right
_NCELLS = SIZE * SIZE
_NONE_KEY = 200 * _NCELLS  # larger than any d2 * 64 + cell; a multiple of 64 -> cell 0


def _cell(x: int, y: int) -> int:
    """Cell index ``x * 8 + y`` (its order is the tie-break order: x first, then y)."""
    return x * SIZE + y


class FindMilk(BatchedTask):
    """FindMilk, ``num_envs`` copies at once.

    ``layout``: `LAYOUTS`; ``tie_break``: ``"first"`` (smallest ``(x, y)``) or ``"random"``
    (the authors' environment); ValueError for another.
    """

    name: ClassVar[str] = "findmilk"
    gym_id: ClassVar[str] = "amuled/FindMilk-v0"
    action_names: ClassVar[tuple[str, ...]] = ("up", "down", "left", "right")
    obs_names: ClassVar[tuple[str, ...]] = (
        "x", "y", "milk_x", "milk_y", "cry_x", "cry_y", "sleep_x", "sleep_y",
    )  # fmt: skip
    obs_low: ClassVar[tuple[float, ...]] = (0.0,) * 8
    obs_high: ClassVar[tuple[float, ...]] = (float(SIZE - 1),) * 8
    metric_names: ClassVar[tuple[str, ...]] = ("crying_pacified", "sleeping_woken", "reached_milk")
    grid_size: ClassVar[int] = SIZE
    human_feedback: ClassVar[bool] = True

    def _init_task(self, layout: str = "paper", tie_break: str = "first") -> None:
        if layout not in LAYOUTS:
            raise ValueError(f"layout: expected one of {', '.join(LAYOUTS)}, got {layout!r}")
        if tie_break not in TIE_BREAKS:
            raise ValueError(
                f"tie_break: expected one of {', '.join(TIE_BREAKS)}, got {tie_break!r}"
            )
        self.layout = layout
        self.tie_break = tie_break
        n, dev = self.num_envs, self.device
        i64 = torch.int64
        cells = torch.arange(_NCELLS, device=dev)
        xs, ys = cells // SIZE, cells % SIZE
        self._xy = torch.stack([xs, ys], 1).to(torch.float32)  # [64, 2]
        move = []
        for c in range(_NCELLS):
            x, y = divmod(c, SIZE)
            for step_x, step_y in _MOVES:
                nx, ny = x + step_x, y + step_y
                move.append(_cell(nx, ny) if 0 <= nx < SIZE and 0 <= ny < SIZE else c)
        self._move = torch.tensor(move, dtype=i64, device=dev)  # [(cell, action)] -> cell
        dx = xs[:, None] - xs[None, :]
        dy = ys[:, None] - ys[None, :]
        self._d2 = (dx * dx + dy * dy).reshape(-1)  # [(cell, cell)] squared distance
        sleep = [_cell(*p) for p in SLEEPING]
        cry = [_cell(*p) for p in CRYING]
        self._full_sleep = torch.tensor((1 << len(SLEEPING)) - 1, dtype=i64, device=dev)
        self._full_cry = torch.tensor((1 << len(CRYING)) - 1, dtype=i64, device=dev)
        self._sleep_bits = self._full_sleep.repeat(n)  # bit j: sleeping baby j still there
        self._cry_bits = self._full_cry.repeat(n)  # bit j: crying baby j still there
        self._reward_goal = torch.tensor(20.0, device=dev)
        self._reward_step = torch.tensor(-1.0, device=dev)
        if layout == "paper":
            self._start = torch.full((n,), _cell(*START), dtype=i64, device=dev)
            self._milk = torch.full((n,), _cell(*MILK), dtype=i64, device=dev)
            self._sleep_cell = torch.tensor([sleep], dtype=i64, device=dev)  # [1, 6]
            self._cry_cell = torch.tensor([cry], dtype=i64, device=dev)  # [1, 5]
            self._cell_base = torch.zeros((), dtype=i64, device=dev)
            self._sleep_bit_of_cell = self._bit_table(sleep)
            self._cry_bit_of_cell = self._bit_table(cry)
            self._near_sleep = self._nearest_table(sleep)
            self._near_cry = self._nearest_table(cry)
            row = [*START, *MILK, *CRYING[0], *SLEEPING[0]]
            self._initial_obs = torch.tensor(row, dtype=torch.float32, device=dev)
        else:
            self._start = torch.zeros(n, dtype=i64, device=dev)
            self._milk = torch.zeros(n, dtype=i64, device=dev)
            self._sleep_cell = torch.tensor([sleep], dtype=i64, device=dev).repeat(n, 1)
            self._cry_cell = torch.tensor([cry], dtype=i64, device=dev).repeat(n, 1)
            self._cell_base = torch.arange(n, dtype=i64, device=dev) * _NCELLS
            self._sleep_bit_of_cell = torch.zeros(n * _NCELLS, dtype=i64, device=dev)
            self._cry_bit_of_cell = torch.zeros(n * _NCELLS, dtype=i64, device=dev)
        self._pos = self._start.clone()
        self.use_tables = layout == "paper"  # False: the generic nearest-baby search

    def _bit_table(self, babies: list[int]) -> torch.Tensor:
        """``[64]``: the bit of the baby on each cell (0 for an empty cell)."""
        table = [0] * _NCELLS
        for j, c in enumerate(babies):
            table[c] = 1 << j
        return torch.tensor(table, dtype=torch.int64, device=self.device)

    def _nearest_table(self, babies: list[int]) -> torch.Tensor:
        """``[64 * 2**k]``: nearest remaining baby's cell for (robot cell, remaining bits)."""
        k = len(babies)
        pos = torch.arange(_NCELLS, device=self.device)[:, None]
        bits = torch.arange(1 << k, device=self.device)[None, :]
        best = torch.full((_NCELLS, 1 << k), _NONE_KEY, dtype=torch.int64, device=self.device)
        for j, c in enumerate(babies):
            key = self._d2[pos * _NCELLS + c] * _NCELLS + c
            best = torch.where((bits >> j) & 1 == 1, torch.minimum(best, key), best)
        return (best % _NCELLS).reshape(-1)

    def _advance(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        new = self._move.index_select(0, self._pos * 4 + actions)
        where = self._cell_base + new
        hit_cry = self._cry_bit_of_cell.index_select(0, where) & self._cry_bits
        hit_sleep = self._sleep_bit_of_cell.index_select(0, where) & self._sleep_bits
        self._cry_bits = self._cry_bits ^ hit_cry
        self._sleep_bits = self._sleep_bits ^ hit_sleep
        pacified = hit_cry != 0
        woken = hit_sleep != 0
        reached = new == self._milk
        self._pos = new
        r_env = torch.where(reached, self._reward_goal, self._reward_step)
        r_shaping = pacified.to(torch.float32) - woken.to(torch.float32)
        events = {"crying_pacified": pacified, "sleeping_woken": woken, "reached_milk": reached}
        return r_env, r_shaping, reached, events

    def _episode_extras(self, episode: dict[str, torch.Tensor]) -> None:
        episode["reached_milk"] = episode["reached_milk"] > 0
        episode["steps_to_milk"] = episode["length"]

    def _reset_where(self, mask: torch.Tensor) -> None:
        if self.layout == "random":
            ids = mask.nonzero().squeeze(1)
            if ids.numel():
                self._random_layout(ids)
        self._pos = torch.where(mask, self._start, self._pos)
        self._cry_bits = torch.where(mask, self._full_cry, self._cry_bits)
        self._sleep_bits = torch.where(mask, self._full_sleep, self._sleep_bits)

    def _random_layout(self, ids: torch.Tensor) -> None:
        """Draw start, milk and babies on distinct cells for the copies ``ids``."""
        perm = self._draw_many(ids, _NCELLS).argsort(dim=1, stable=True)  # random permutation
        self._start[ids] = perm[:, 0]
        self._milk[ids] = perm[:, 1]
        ns, nc = len(SLEEPING), len(CRYING)
        candidates = perm[:, 2 : 2 + ns + nc + 1]
        # babies avoid cell (0, 0), the "none left" marker of the observation
        order = (candidates == 0).to(torch.int8).argsort(dim=1, stable=True)
        babies = candidates.gather(1, order[:, : ns + nc])
        sleep = babies[:, :ns].sort(1).values
        cry = babies[:, ns:].sort(1).values
        self._sleep_cell[ids] = sleep
        self._cry_cell[ids] = cry
        base = self._cell_base[ids, None]
        for table, cells in ((self._sleep_bit_of_cell, sleep), (self._cry_bit_of_cell, cry)):
            rows = (base + torch.arange(_NCELLS, device=self.device)).reshape(-1)
            table[rows] = 0
            bits = torch.ones_like(cells) << torch.arange(cells.shape[1], device=self.device)
            table[(base + cells).reshape(-1)] = bits.reshape(-1)

    def _nearest(self, cells: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
        """Cell of a nearest remaining baby per copy, ties by ``tie_break`` (0: none left)."""
        n, k = self.num_envs, cells.shape[1]
        cells = cells.expand(n, -1)
        d2 = self._d2.index_select(0, (self._pos[:, None] * _NCELLS + cells).reshape(-1))
        d2 = d2.reshape(n, k)
        alive = self._alive(bits, k)
        if self.tie_break == "first":
            # int32: torch's int64 min-reduction over a short last dimension is very slow
            key = torch.where(alive, (d2 * _NCELLS + cells).to(torch.int32), _NONE_KEY)
            return (key.amin(1) % _NCELLS).to(torch.int64)
        ids = torch.arange(n, device=self.device)
        rank = self._draw_many(ids, k).argsort(dim=1).argsort(dim=1)  # a random order
        key = torch.where(alive, d2 * k + rank, torch.iinfo(torch.int64).max)
        nearest = cells.gather(1, key.argmin(1, keepdim=True)).squeeze(1)
        return torch.where(alive.any(1), nearest, torch.zeros_like(nearest))

    def _nearest_cells(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Cells of the nearest remaining crying and sleeping baby (0 = none left)."""
        if self.use_tables and self.tie_break == "first":
            cry = self._near_cry.index_select(0, self._pos * (1 << len(CRYING)) + self._cry_bits)
            sleep = self._near_sleep.index_select(
                0, self._pos * (1 << len(SLEEPING)) + self._sleep_bits
            )
            return cry, sleep
        return (
            self._nearest(self._cry_cell, self._cry_bits),
            self._nearest(self._sleep_cell, self._sleep_bits),
        )

    def _observe(self) -> torch.Tensor:
        cry, sleep = self._nearest_cells()
        cells = torch.stack([self._pos, self._milk, cry, sleep], 1).reshape(-1)
        return self._xy.index_select(0, cells).reshape(self.num_envs, 8)

    @staticmethod
    def _alive(bits: torch.Tensor, k: int) -> torch.Tensor:
        return (bits[:, None] >> torch.arange(k, device=bits.device)) & 1 == 1

    @property
    def position(self) -> torch.Tensor:
        """Robot position ``(x, y)`` per copy (int64 ``[num_envs, 2]``)."""
        return torch.stack([self._pos // SIZE, self._pos % SIZE], 1)

    def crying_left(self) -> torch.Tensor:
        """Return the number of crying babies not yet pacified per copy."""
        return self._alive(self._cry_bits, len(CRYING)).sum(1)

    def sleeping_left(self) -> torch.Tensor:
        """Return the number of sleeping babies not yet woken per copy."""
        return self._alive(self._sleep_bits, len(SLEEPING)).sum(1)

    def baby_positions(self, env_id: int = 0) -> dict[str, list[tuple[int, int]]]:
        """Return the remaining babies of one copy: ``{"crying": [...], "sleeping": [...]}``."""
        env_id = self._env_id(env_id)
        out: dict[str, list[tuple[int, int]]] = {}
        for kind, cells, bits in (
            ("crying", self._cry_cell, self._cry_bits),
            ("sleeping", self._sleep_cell, self._sleep_bits),
        ):
            row = cells[min(env_id, cells.shape[0] - 1)].tolist()
            b = int(bits[env_id])
            out[kind] = [divmod(c, SIZE) for j, c in enumerate(row) if (b >> j) & 1]
        return out

    def sleeping_positions(self) -> torch.Tensor:
        """Return every sleeping baby's ``(x, y)`` ``[num_envs, 6, 2]``, ``(-1, -1)`` once woken."""
        cells = self._sleep_cell.expand(self.num_envs, -1)
        xy = torch.stack([cells // SIZE, cells % SIZE], 2)
        alive = self._alive(self._sleep_bits, len(SLEEPING))
        return torch.where(alive[:, :, None], xy, -1)

    @classmethod
    def prompt_variables_from_obs(
        cls, obs: np.ndarray, *, num_crying: int | None = None, **extra: Any
    ) -> dict[str, Any]:
        """Return the FindMilk prompt variables of one observation (8 floats) and ``extra``.

        ``grid_size``, ``num_crying``, the entries as floats (the recordings print ``x=2.0``),
        ``crying_around`` / ``sleeping_around`` (1 while one remains).

        Raises:
            ValueError: ``obs`` is not 8 numbers or ``num_crying`` is missing or negative.
        """
        values = cls._obs_values(obs)
        if num_crying is None or int(num_crying) < 0:
            raise ValueError(
                f"num_crying: expected the number of crying babies left (>= 0), got {num_crying!r}"
            )
        out: dict[str, Any] = {"grid_size": SIZE, "num_crying": int(num_crying)}
        out.update((k, float(v)) for k, v in zip(cls.obs_names, values, strict=True))
        out["crying_around"] = int(values[4] != 0 or values[5] != 0)
        out["sleeping_around"] = int(values[6] != 0 or values[7] != 0)
        out.update(extra)
        return out

    def _prompt_extras(self, ids: torch.Tensor) -> list[dict[str, Any]]:
        return [{"num_crying": int(k)} for k in self.crying_left()[ids].tolist()]

    def _grid_chars(self, env_id: int) -> list[list[str]]:
        grid = [["." for _ in range(SIZE)] for _ in range(SIZE)]  # grid[y][x]
        babies = self.baby_positions(env_id)
        for x, y in babies["sleeping"]:
            grid[y][x] = "S"
        for x, y in babies["crying"]:
            grid[y][x] = "C"
        mx, my = divmod(int(self._milk[env_id]), SIZE)
        grid[my][mx] = "M"
        rx, ry = divmod(int(self._pos[env_id]), SIZE)
        grid[ry][rx] = "R"
        return grid

    def render_ansi(self, env_id: int = 0) -> str:
        """Return the grid as text, ``y = 7`` on top (R robot, M milk, C crying, S sleeping)."""
        env_id = self._env_id(env_id)
        grid = self._grid_chars(env_id)
        lines = [
            f"FindMilk step {int(self._t[env_id])}/{self.max_steps}  "
            f"crying left {int(self.crying_left()[env_id])}  "
            f"sleeping left {int(self.sleeping_left()[env_id])}"
        ]
        lines += [f"{y} " + " ".join(grid[y]) for y in range(SIZE - 1, -1, -1)]
        lines.append("  " + " ".join(str(x) for x in range(SIZE)))
        return "\n".join(lines) + "\n"

    def render_rgb(self, env_id: int = 0, cell: int = 32) -> np.ndarray:
        """Return an RGB image (uint8 ``[8*cell, 8*cell, 3]``), ``y = 7`` at the top row."""
        env_id = self._env_id(env_id)
        colours = {
            ".": (255, 255, 255),
            "S": (60, 170, 80),
            "C": (220, 60, 60),
            "M": (60, 110, 230),
            "R": (40, 40, 40),
        }
        grid = self._grid_chars(env_id)
        img = paint_cells(grid[::-1], colours, cell, background=255)  # y = 7 on top
        img[::cell, :] = (200, 200, 200)
        img[:, ::cell] = (200, 200, 200)
        return img
