"""``DeliberationEnv``: one task, an actor and a panel of moral-cluster agents (PettingZoo, v0).

Agents, spaces, rewards and ``infos`` keys: docs/deliberation.md, "DeliberationEnv".
"""

from __future__ import annotations

import contextlib
import copy
import functools
import string
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import torch
from gymnasium import spaces
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from amuled_ma.deliberation.mdp import BatchedDeliberation
from amuled_ma.files.resources import prompts_dir

if TYPE_CHECKING:
    from amuled_ma.deliberation.panel import MoralPanel

ACTOR = "actor"


def project_to_simplex(v: npt.ArrayLike) -> np.ndarray:
    """Euclidean projection onto the probability simplex; NaN or inf gives uniform."""
    v = np.asarray(v, dtype=np.float64).reshape(-1)
    n = v.size
    if n == 0:
        raise ValueError("cannot project an empty vector onto the simplex")
    if not np.all(np.isfinite(v)):
        return np.full(n, 1.0 / n)
    u = np.sort(v)[::-1]
    css = np.cumsum(u)
    j = np.arange(1, n + 1)
    rho = int(np.nonzero(u + (1.0 - css) / j > 0)[0][-1]) + 1
    theta = (1.0 - css[rho - 1]) / rho
    x = np.maximum(v + theta, 0.0)
    return x / x.sum()  # exact to rounding already; this removes the last ulp of drift


class DeliberationEnv(ParallelEnv):
    """The actor and the moral clusters around one task (docs/deliberation.md).

    ``render_mode``: ``None``, ``"ansi"`` or ``"rgb_array"``; ``max_steps`` None keeps the
    task's limit; ``clusters`` defaults to the shipped panel; ``clusters_dirs`` are folders of
    user cluster files, overriding the shipped ones; ``task_options`` go to the task.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012 - PettingZoo convention
        "name": "amuled_deliberation_v0",
        "render_modes": ["ansi", "rgb_array"],
        "is_parallelizable": True,
    }

    def __init__(
        self,
        task_name: str = "findmilk",
        clusters: Sequence[str] | None = None,
        fusion_rule: str = "bjs-dst",
        *,
        r_env_weight: float = 1.0,
        feedback_coef: float = 1.0,
        shaping_coef: float = 0.0,
        max_steps: int | None = None,
        seed: int | None = None,
        render_mode: str | None = None,
        prompt_max_length: int = 16384,
        render_state_prompt: Callable[[str, Mapping[str, Any]], str] | None = None,
        task_options: Mapping[str, Any] | None = None,
        clusters_dirs: Sequence[str | Path] = (),
    ) -> None:
        from amuled_ma.clusters import ClusterRegistry, default_registry
        from amuled_ma.fusion import fuse
        from amuled_ma.tasks import get_task
        from amuled_ma.tasks.prompts import render_state_prompt as render

        if render_mode not in (None, "ansi", "rgb_array"):
            raise ValueError(
                f"render_mode: expected None, 'ansi' or 'rgb_array', got {render_mode!r}"
            )
        registry = ClusterRegistry.load(clusters_dirs) if clusters_dirs else default_registry()
        if clusters is None:
            clusters = [c.name for c in registry.panel()]
        clusters = [registry.get(str(c)).name if str(c) in registry else str(c) for c in clusters]
        if not clusters or ACTOR in clusters or len(set(clusters)) != len(clusters):
            raise ValueError(
                f"clusters: expected distinct names other than 'actor', got {clusters}"
            )
        task_cls = get_task(task_name)
        kwargs: dict[str, Any] = dict(task_options or {})
        if max_steps is not None:
            kwargs["max_steps"] = max_steps
        self.task = task_cls(1, seed=seed, shaping_coef=shaping_coef, **kwargs)
        # the deliberation MDP with one copy; this env's arbiter hands it the fused belief
        self.mdp = BatchedDeliberation(
            self.task, None, task_weight=r_env_weight, feedback_coef=feedback_coef
        )
        self.task_name = task_cls.name
        self.action_names = tuple(task_cls.action_names)
        self.cluster_names = tuple(clusters)
        self.fusion_rule = fusion_rule
        self.render_mode = render_mode
        self.prompt_max_length = int(prompt_max_length)
        self._render_prompt = render_state_prompt or render
        self._fuse = fuse
        self.possible_agents = [ACTOR, *self.cluster_names]
        self.agents: list[str] = []
        self._obs = np.zeros(self.task.obs_dim, dtype=np.float32)
        self._prompt = ""
        self._last: tuple[int, dict[str, Any]] | None = None  # the last step, for render()
        # Fail now, not at the first step, on an unknown rule.
        k, a = len(self.cluster_names), len(self.action_names)
        fuse(np.full((k, a), 1.0 / a), fusion_rule, return_diagnostics=True)

    @functools.cache  # noqa: B019 - one env, a handful of agents
    def observation_space(self, agent: str) -> spaces.Space:
        """Return the observation space of ``agent`` (the same object every call)."""
        task = self.task
        box = spaces.Box(
            low=np.asarray(task.obs_low, dtype=np.float32),
            high=np.asarray(task.obs_high, dtype=np.float32),
            dtype=np.float32,
        )
        if agent == ACTOR:
            return box
        self._check_agent(agent)
        chars = set(string.printable)  # and those of the task's shipped template, if any
        with contextlib.suppress(OSError):
            chars |= set((prompts_dir() / "tasks" / f"{self.task_name}.md").read_text("utf-8"))
        text = spaces.Text(self.prompt_max_length, min_length=0, charset=frozenset(chars))
        return spaces.Dict({"prompt": text, "obs": box})

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        """Return the action space of ``agent`` (the same object every call)."""
        n = len(self.action_names)
        if agent == ACTOR:
            return spaces.Discrete(n)
        self._check_agent(agent)
        return spaces.Box(low=0.0, high=1.0, shape=(n,), dtype=np.float32)

    def _check_agent(self, agent: str) -> None:
        if agent not in self.possible_agents:
            raise KeyError(f"unknown agent {agent!r}; agents: {self.possible_agents}")

    def _state_prompt(self) -> str:
        return self._render_prompt(self.task_name, self.task.prompt_variables()[0])

    def _observations(self) -> dict[str, Any]:
        cluster = {
            name: {"prompt": self._prompt, "obs": self._obs.copy()} for name in self.cluster_names
        }
        return {ACTOR: self._obs.copy(), **cluster}

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
        """Reset the task and return every agent's first observation and an empty info."""
        self._obs = _row(self.mdp.reset(seed=seed))
        self._prompt = self._state_prompt()
        self._last = None
        self.agents = list(self.possible_agents)
        return self._observations(), {agent: {} for agent in self.agents}

    def step(self, actions: Mapping[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Fuse the cluster beliefs, step the task with the actor's action, reward everyone.

        Raises:
            RuntimeError: ``step`` after the episode ended (call ``reset``).
            KeyError: The actor's action is missing.
            ValueError: The actor's action is out of range.
        """
        if not self.agents:
            raise RuntimeError("step() called with no live agents; call reset() first")
        if ACTOR not in actions:
            raise KeyError("actions: missing the 'actor' action")
        a = int(np.asarray(actions[ACTOR]).reshape(()))
        n = len(self.action_names)
        if not 0 <= a < n:
            raise ValueError(f"actions['actor']: expected 0..{n - 1}, got {a}")
        beliefs = np.empty((len(self.cluster_names), n))
        for k, name in enumerate(self.cluster_names):
            value = actions.get(name)
            beliefs[k] = np.full(n, 1.0 / n) if value is None else project_to_simplex(value)
        diag = self._fuse(beliefs, self.fusion_rule, return_diagnostics=True)
        fused = np.asarray(diag.fused, dtype=np.float64)
        weights = np.asarray(diag.weights, dtype=np.float64)
        conflicts = np.asarray(diag.conflicts, dtype=np.float64).reshape(-1)

        out = self.mdp.step(
            torch.tensor([a], dtype=torch.long), fused=torch.from_numpy(fused).reshape(1, n)
        )
        info = out.info
        terminated, truncated = bool(out.terminated[0]), bool(out.truncated[0])
        done = terminated or truncated
        self._obs = _row(info["final_obs"] if done and "final_obs" in info else out.obs)
        named = dict(zip(self.cluster_names, weights.tolist(), strict=True))
        rewards = {ACTOR: float(out.reward[0]), **named}
        common = {
            "fused": fused,
            "beliefs": beliefs,
            "weights": named,
            "conflict": float(conflicts[0]) if conflicts.size else 0.0,
            "conflicts": conflicts,
            "r_env": float(info["r_env"][0]) if "r_env" in info else float(out.r_task[0]),
            "r_shaping": float(info["r_shaping"][0]) if "r_shaping" in info else 0.0,
            "r_feedback": float(fused[a]),
        }
        self._last = (a, common)
        infos = {agent: copy.deepcopy(common) for agent in self.agents}  # each owns its arrays
        term = dict.fromkeys(self.agents, terminated)
        trunc = dict.fromkeys(self.agents, truncated and not terminated)
        # No cluster is asked about a finished episode: its final prompt is empty.
        self._prompt = "" if done else self._state_prompt()
        observations = self._observations()
        if done:
            self.agents = []
        return observations, rewards, term, trunc, infos

    def panel_actions(self, panel: MoralPanel) -> dict[str, np.ndarray]:
        """Every live cluster agent's belief answered by ``panel`` now (`KeyError`: not in it)."""
        names = list(getattr(panel, "clusters", []))
        missing = [c for c in self.cluster_names if c not in names]
        if missing:
            raise KeyError(f"panel has no cluster(s) {missing}; it has {names}")
        out = panel.fused(self._obs[None, :], self.task.prompt_variables())
        return {
            c: out.beliefs[0, names.index(c)].astype(np.float32)
            for c in self.cluster_names
            if c in self.agents
        }

    def state(self) -> np.ndarray:
        """Return the global state: the task observation."""
        return self._obs.copy()

    def render(self) -> str | np.ndarray | None:
        """Render in ``render_mode``: ``"ansi"`` text with the last step's panel, or RGB uint8."""
        if self.render_mode == "rgb_array":
            return self.task.render_rgb(0)
        if self.render_mode != "ansi":
            return None
        text = self.task.render_ansi(0)
        if self._last is None:
            return text
        action, info = self._last
        width = max(len(name) for name in (*self.cluster_names, "fused"))
        cols = [name[:7].rjust(7) for name in self.action_names]
        lines = [
            f"last step: actor {self.action_names[action]}, conflict K {info['conflict']:.3f}",
            f"{'':<{width}}  {' '.join(cols)}   weight",
        ]
        for k, name in enumerate(self.cluster_names):
            row = " ".join(f"{v:7.3f}" for v in info["beliefs"][k])
            lines.append(f"{name:<{width}}  {row}   {info['weights'][name]:6.3f}")
        row = " ".join(f"{v:7.3f}" for v in info["fused"])
        lines.append(f"{'fused':<{width}}  {row}")
        return text + "\n".join(lines) + "\n"

    def close(self) -> None:
        """Nothing to release."""


def _row(obs: npt.ArrayLike | torch.Tensor) -> np.ndarray:
    if hasattr(obs, "detach"):
        obs = obs.detach().cpu().numpy()
    return np.asarray(obs, dtype=np.float32).reshape(-1).copy()


def parallel_env(task_name: str = "findmilk", **kwargs: Any) -> DeliberationEnv:
    """The deliberation env of ``task_name``, as PettingZoo's env modules offer it."""
    return DeliberationEnv(task_name, **kwargs)


def env(task_name: str = "findmilk", **kwargs: Any) -> AECEnv:
    """Its AEC form: `parallel_env` through PettingZoo's ``parallel_to_aec``."""
    return parallel_to_aec(parallel_env(task_name, **kwargs))
