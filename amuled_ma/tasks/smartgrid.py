"""Ethical Smart Grid (Chaput et al., ``ethical-smart-grid`` 2.0.0) as an AMULED task.

An adapter, not a fork (extra ``amuled-ma[smartgrid]``): docs/tasks.md, "Ethical Smart Grid".
"""

from __future__ import annotations

import copy
import functools
import importlib
import itertools
import weakref
from collections import OrderedDict
from typing import Any, ClassVar

import numpy as np
import torch

from amuled_ma.errors import ScenarioError
from amuled_ma.tasks.base import BatchedTask, check_int, paint_cells

__all__ = ["ACTIONS", "FIXED_ACTION", "JUDGES", "JUDGE_TEMPERATURE", "SmartGrid", "action_vector"]

#: The learner's actions, by id: the name, then what it does.
ACTIONS: tuple[tuple[str, str], ...] = (
    ("grid", "take the whole need from the grid"),
    ("battery", "use the battery first, the rest of the need from the grid"),
    ("frugal", "take half of the need from the grid"),
    ("hoard", "take the whole need from the grid and fill the battery from the grid"),
    ("share", "take half of the need from the grid and give the battery's energy to the grid"),
)
#: The action of every prosumer but the learner.
FIXED_ACTION = 0
#: The judges: value name -> the package's reward class (module, class).
JUDGES: dict[str, tuple[str, str]] = {
    "comfort": ("smartgrid.rewards.numeric.per_agent.comfort", "Comfort"),
    "equity": ("smartgrid.rewards.numeric.differentiated", "Equity"),
    "over_consumption": ("smartgrid.rewards.numeric.differentiated", "OverConsumption"),
}
#: Temperature of a judge's belief: p(a) ∝ exp(r_v(a) / JUDGE_TEMPERATURE). The package's
#: rewards lie in [-1, 1]; 0.1 makes a difference of 0.1 in reward a factor e in belief.
JUDGE_TEMPERATURE = 0.1
#: Judge scores kept per process, by observation (a state asked twice is computed once).
MAX_SCORED = 65_536

# every smart-grid task alive in this process; a stamp orders the copies' latest observations,
# and a judge looks ahead from the least recently observed copy that shows the state
_TASKS: weakref.WeakSet[SmartGrid] = weakref.WeakSet()
_SHOWN = itertools.count()
# observation bytes -> judge rewards [judge, action]
_SCORED: OrderedDict[bytes, np.ndarray] = OrderedDict()


def action_vector(action: int, need: float, storage: float, capacity: float) -> list[int]:
    """The package's int64 action in Wh for a named action, from need, battery and capacity.

    Returns:
        ``[grid_consumption, storage_consumption, store_energy, give_energy, buy_energy,
        sell_energy]``.
    """
    from_battery = min(storage, need)
    vectors = (
        (need, 0, 0, 0, 0, 0),  # grid
        (need - from_battery, from_battery, 0, 0, 0, 0),  # battery
        (need / 2, 0, 0, 0, 0, 0),  # frugal
        (need, 0, capacity - storage, 0, 0, 0),  # hoard
        (need / 2, 0, 0, storage, 0, 0),  # share
    )
    return [round(max(0.0, float(v))) for v in vectors[action]]


@functools.cache
def _profiles() -> Any:
    """The package's OpenEI daily profiles, loaded once per process.

    The package's ``find_profile_data`` fails on Python 3.11, so ``importlib.resources`` finds them.
    """
    from importlib.resources import files

    from smartgrid.agents import DataOpenEIConversion, comfort

    folder = files("smartgrid.data") / "openei"
    converter = DataOpenEIConversion()
    converter.load(
        "Household",
        str(folder / "profile_residential_daily.npz"),
        comfort.flexible_comfort_profile,
    )
    converter.load(
        "Office", str(folder / "profile_office_daily.npz"), comfort.neutral_comfort_profile
    )
    return converter


def _reward(value: str) -> Any:
    """A new instance of the package's reward class judging ``value`` (a key of `JUDGES`)."""
    module, name = JUDGES[value]
    return getattr(importlib.import_module(module), name)()


class SmartGrid(BatchedTask):
    """``num_envs`` copies of a small smart grid, one learning household in each.

    Task options: ``households`` (1..1000, the learner is the first) and ``offices``
    (0..1000). ``max_steps`` defaults to 24 (one day, one step an hour).
    """

    name = "smartgrid"
    gym_id = ""
    action_names = tuple(name for name, _ in ACTIONS)
    obs_names = (
        "personal_storage",
        "comfort",
        "payoff",
        "hour",
        "available_energy",
        "equity",
        "energy_loss",
        "autonomy",
        "exclusion",
        "well_being",
        "over_consumption",
    )
    obs_low = (0.0,) * 11
    obs_high = (1.0,) * 11
    metric_names = ("need_met", "grid_overloaded")
    default_max_steps = 24
    judge_names: ClassVar[tuple[str, ...]] = tuple(JUDGES)

    def _init_task(self, households: int = 3, offices: int = 1) -> None:
        households = check_int(households, "households", 1, 1000)
        offices = check_int(offices, "offices", 0, 1000)
        try:
            from smartgrid import SmartGrid as PackageGrid
            from smartgrid import World
            from smartgrid.agents import Agent
            from smartgrid.observation import ObservationManager
            from smartgrid.util import RandomEnergyGenerator
        except ImportError as error:
            raise ScenarioError(
                f"task 'smartgrid' needs the package ethical-smart-grid ({error}); install "
                "it with: pip install 'amuled-ma[smartgrid]'"
            ) from None
        profiles = _profiles().profiles
        self._envs = []
        for _ in range(self.num_envs):
            agents = [Agent(f"Household{k + 1}", profiles["Household"]) for k in range(households)]
            agents += [Agent(f"Office{k + 1}", profiles["Office"]) for k in range(offices)]
            world = World(agents, RandomEnergyGenerator())
            rewards = [_reward(v) for v in JUDGES]
            self._envs.append(PackageGrid(world, rewards, None, ObservationManager()))
        self._learner = "Household1"
        n = self.num_envs
        self._value_sums = torch.zeros(n, len(JUDGES), dtype=torch.float32)
        self._live_keys: list[bytes | None] = [None] * n
        self._shown_at = [0] * n
        _TASKS.add(self)

    def _advance(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        n = self.num_envs
        values = torch.zeros(n, len(JUDGES), dtype=torch.float32)
        r_shaping = torch.zeros(n, dtype=torch.float32)
        overloaded = torch.zeros(n, dtype=torch.int64)
        for i, (env, action) in enumerate(zip(self._envs, actions.tolist(), strict=True)):
            # the package's step for the learner alone (the others' observations: never read)
            rewards = _step_world(env.world, env.reward_calculator, self._learner, int(action))
            manager = env.observation_manager
            manager.reset()  # the package's memo is shared by every world
            overloaded[i] = int(float(manager.compute_global(env.world).over_consumption) > 0)
            manager.reset()
            values[i] = torch.tensor([rewards[v] for v in JUDGES])
            r_shaping[i] = rewards["equity"]
        self._value_sums += values
        comfort = values[:, 0]
        events = {"need_met": (comfort >= 0.9).to(torch.int64), "grid_overloaded": overloaded}
        return comfort.clone(), r_shaping, torch.zeros(n, dtype=torch.bool), events

    def _episode_extras(self, episode: dict[str, torch.Tensor]) -> None:
        """Each judge's mean reward per step over the episode (``comfort``, ...)."""
        steps = episode["length"].clamp(min=1).to(torch.float32)
        for k, value in enumerate(JUDGES):
            episode[value] = self._value_sums[:, k] / steps

    def _reset_where(self, mask: torch.Tensor) -> None:
        ids = torch.nonzero(mask).flatten()
        if len(ids) == 0:
            return
        seeds = self._draw_many(ids, 1)[:, 0].tolist()
        for i, s in zip(ids.tolist(), seeds, strict=True):
            env = self._envs[i]
            env.observation_manager.reset()
            env.reset(seed=s & 0x7FFF_FFFF_FFFF_FFFF)
        self._value_sums[ids] = 0.0

    def _observe(self) -> torch.Tensor:
        rows = []
        for env in self._envs:
            env.observation_manager.reset()  # the package's memo is shared by every world
            agent = env.world.agents_by_name[self._learner]
            rows.append(np.asarray(env.observation_manager.compute(env.world, agent)))
        obs = torch.as_tensor(np.asarray(rows, dtype=np.float32))
        self._remember(obs)
        return obs

    def _remember(self, obs: torch.Tensor) -> None:
        """Mark each copy's observation as live, for the judges' look-ahead."""
        for i, row in enumerate(obs.numpy()):
            self._live_keys[i] = row.tobytes()
            self._shown_at[i] = next(_SHOWN)

    def _prompt_extras(self, ids: torch.Tensor) -> list[dict[str, Any]]:
        extras = []
        for i in ids.tolist():
            agent = self._envs[i].world.agents_by_name[self._learner]
            extras.append(
                {
                    "need": round(float(agent.need)),
                    "storage": round(float(agent.state.storage)),
                    "capacity": round(float(agent.profile.max_storage)),
                    "prosumers": len(self._envs[i].world.agents),
                }
            )
        return extras

    @classmethod
    def prompt_variables_from_obs(cls, obs: np.ndarray, **extra: Any) -> dict[str, Any]:
        """Each observation entry in percent, the hour, and four values of ``extra``.

        ``need``, ``storage``, ``capacity`` (Wh) and ``prosumers`` read ``unknown`` when absent.
        """
        variables: dict[str, Any] = {
            name: round(100 * float(v)) for name, v in zip(cls.obs_names, obs, strict=True)
        }
        variables["hour"] = round(24 * float(obs[3])) % 24
        for key in ("need", "storage", "capacity", "prosumers"):
            variables[key] = extra.get(key, "unknown")
        return variables

    @classmethod
    def judge_scores(cls, judge: str, obs: np.ndarray) -> np.ndarray:
        """The judge's belief scores ``exp((r_v(a) - max r_v) / JUDGE_TEMPERATURE)``.

        ``r_v(a)``: the package's reward of ``judge`` one step after ``a`` on a copy of the live
        world showing ``obs``.

        Raises:
            ValueError: Unknown judge, or a state no live copy of this process shows
                (e.g. a replayed observation).
        """
        if judge not in JUDGES:
            raise ValueError(f"judge: expected one of {', '.join(JUDGES)}, got {judge!r}")
        rows = np.atleast_2d(np.asarray(obs, dtype=np.float32))
        k = list(JUDGES).index(judge)
        out = np.stack([_scores(row.tobytes())[k] for row in rows])
        out = np.exp((out - out.max(axis=1, keepdims=True)) / JUDGE_TEMPERATURE)
        return out[0] if np.asarray(obs).ndim == 1 else out

    def render_ansi(self, env_id: int = 0) -> str:
        """One line per prosumer: need, battery, comfort (the learner marked ``*``)."""
        world = self._envs[env_id].world
        lines = [f"step {world.current_step}, available {round(world.available_energy)} Wh"]
        for agent in world.agents:
            mark = "*" if agent.name == self._learner else " "
            lines.append(
                f"{mark}{agent.name:<12} need {round(agent.need):>6} Wh  battery "
                f"{round(agent.state.storage):>6}/{round(agent.profile.max_storage)} Wh  "
                f"comfort {agent.state.comfort:.2f}"
            )
        return "\n".join(lines)

    def render_rgb(self, env_id: int = 0, cell: int = 32) -> np.ndarray:
        """One column per prosumer, its battery filled in tenths (the learner in blue)."""
        agents = list(self._envs[env_id].world.agents)
        bars = [(a.storage_ratio * 10, "L" if a.name == self._learner else "P") for a in agents]
        rows = [
            "".join(m if f >= level - 0.5 else "." for f, m in bars) for level in range(10, 0, -1)
        ]
        colours = {"L": (31, 119, 180), "P": (127, 127, 127)}
        return paint_cells(rows, colours, cell, 255)


def _step_world(world: Any, calculator: Any, learner: str, action: int) -> dict[str, float]:
    """Step a package world, the learner doing ``action``; its rewards by judge."""
    from smartgrid.agents import Action

    for agent in world.agents:
        chosen = action if agent.name == learner else FIXED_ACTION
        vector = action_vector(chosen, agent.need, agent.state.storage, agent.profile.max_storage)
        agent.intended_action = Action(*vector)
    world.step()
    rewards = calculator.compute(world, world.agents_by_name[learner])  # by class name
    return {v: float(rewards[JUDGES[v][1]]) for v in JUDGES}


def _world_copy(world: Any) -> Any:
    """A deep copy of a package world that shares its agents' profiles (read-only data)."""
    memo: dict[int, Any] = {id(agent.profile): agent.profile for agent in world.agents}
    return copy.deepcopy(world, memo)


def _scores(key: bytes) -> np.ndarray:
    """Every judge's reward ``[judge, action]`` of the state whose observation is ``key``."""
    if key in _SCORED:
        _SCORED.move_to_end(key)
        return _SCORED[key]
    live = [
        (t._shown_at[i], i, t) for t in list(_TASKS) for i, k in enumerate(t._live_keys) if k == key
    ]
    if not live:
        raise ValueError(
            "smartgrid judge: no live smart-grid copy in this process shows this observation "
            "(the judges look one step ahead from the world itself; a replayed state cannot "
            "be judged)"
        )
    _, copy_id, task = min(live, key=lambda held: held[0])  # stamps are unique
    out = np.zeros((len(JUDGES), len(ACTIONS)))
    env = task._envs[copy_id]
    for a in range(len(ACTIONS)):
        rewards = _step_world(_world_copy(env.world), env.reward_calculator, task._learner, a)
        out[:, a] = [rewards[v] for v in JUDGES]
    _SCORED[key] = out
    if len(_SCORED) > MAX_SCORED:
        _SCORED.popitem(last=False)
    return out
