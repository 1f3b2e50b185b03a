"""The learner's view of the deliberation MDP as rsl-rl's ``VecEnv``, with episode totals."""

from __future__ import annotations

from typing import Any

import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from amuled_ma.deliberation.mdp import BatchedDeliberation, as_tensor
from amuled_ma.learn.config import OBS_GROUP


class DeliberationVecEnv(VecEnv):
    """Expose a ``BatchedDeliberation`` as an rsl-rl ``VecEnv`` with one observation group."""

    def __init__(
        self, mdp: BatchedDeliberation, max_episode_length: int = 1000, cfg: dict | None = None
    ) -> None:
        self.mdp = mdp
        self.task = mdp.task
        self.num_envs = mdp.num_envs
        self.num_actions = mdp.num_actions
        self.device = mdp.device
        self.max_episode_length = int(max_episode_length)
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.cfg = cfg or {}
        self._ep_return = torch.zeros(self.num_envs, device=self.device)
        self._ep_shaping = torch.zeros(self.num_envs, device=self.device)
        # finished episodes since the last drain: (column names, table) per step
        self._pending: list[tuple[list[str], torch.Tensor]] = []
        mdp.reset()

    @property
    def obs(self) -> torch.Tensor:
        """The current observations ``[N, obs_dim]``."""
        return self.mdp.obs

    def _wrap(self, obs: torch.Tensor) -> TensorDict:
        return TensorDict({OBS_GROUP: obs}, batch_size=[self.num_envs], device=self.device)

    def _sums(self) -> dict[str, torch.Tensor]:
        """The per-copy accumulators of the episodes running, by their `state_dict` keys."""
        return {
            "episode_length": self.episode_length_buf,
            "episode_return": self._ep_return,
            "episode_shaping": self._ep_shaping,
        }

    def state_dict(self) -> dict[str, Any] | None:
        """The task's state, obs and episode sums for exact resumes (None: unsupported)."""
        if not callable(getattr(self.task, "state_dict", None)):
            return None
        sums = {name: value.clone() for name, value in self._sums().items()}
        return {"task": self.task.state_dict(), "obs": self.mdp.obs.clone(), **sums}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict`; ValueError: another task or number of copies."""
        self.task.load_state_dict(state["task"])
        for name, mine in {"obs": self.mdp.obs, **self._sums()}.items():
            saved = state.get(name)
            if not torch.is_tensor(saved) or saved.shape != mine.shape:
                raise ValueError(f"env state: {name} of shape {tuple(mine.shape)} expected")
            mine.copy_(saved)

    def get_observations(self) -> TensorDict:
        """Return the current observations as a TensorDict with one ``"policy"`` group."""
        return self._wrap(self.mdp.obs)

    def reset(self) -> TensorDict:
        """Reset every copy and return the first observations."""
        obs = self.mdp.reset()
        for value in self._sums().values():
            value.zero_()
        return self._wrap(obs)

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Step every copy (one-hot rows or indices): obs, rewards ``[N]``, dones ``[N]``, extras.

        extras: ``time_outs``, ``log``, the task's ``info``, ``actions`` (and ``feedback``).
        """
        index = actions.argmax(dim=-1) if actions.dim() == 2 else actions.long()
        if index.device != self.device:
            index = index.to(self.device)
        out = self.mdp.step(index)
        info = out.info
        terminated, truncated = out.terminated, out.truncated
        dones = terminated | truncated
        r_env = info.get("r_env")
        if r_env is not None:
            self._ep_return += as_tensor(r_env, torch.float32, self.device)
        else:
            self._ep_return += out.r_task
        r_shaping = info.get("r_shaping")
        if r_shaping is not None:
            self._ep_shaping += as_tensor(r_shaping, torch.float32, self.device)
        self.episode_length_buf += 1
        extras: dict[str, Any] = {
            "time_outs": (truncated & ~terminated).float(),
            "info": info,
            "actions": index,
        }
        if out.feedback is not None:
            extras["feedback"] = out.feedback
        if bool(dones.any()):
            self._finish(info, dones, extras)
        return self._wrap(out.obs), out.reward, dones.float(), extras

    def _finish(self, info: dict[str, Any], dones: torch.Tensor, extras: dict[str, Any]) -> None:
        """Keep the totals of the episodes that ended at this step; reset their accumulators.

        A table ``[done, keys + copy index]`` in float64 (it holds every float32, int < 2**53
        and bool exactly): the columns of ``info["episode"]`` (every copy's accumulators),
        then this env's own sums under names it lacks.
        """
        done_ids = dones.nonzero(as_tuple=False).squeeze(-1)
        columns: dict[str, torch.Tensor] = {}
        for key, value in (info.get("episode") or {}).items():
            if key.startswith("_") or key == "done":
                continue
            tensor = torch.as_tensor(value).reshape(-1)
            if tensor.numel() == self.num_envs:
                columns[key] = tensor.to(torch.float64)
        own = {
            "return_env": self._ep_return,
            "length": self.episode_length_buf,
            "return_shaping": self._ep_shaping,
        }
        for key, tensor in own.items():
            if key not in columns:  # converted only when used: this runs at every step
                columns[key] = tensor.to(torch.float64)
        keys = list(columns)
        table = torch.stack(
            [*columns.values(), torch.arange(self.num_envs, dtype=torch.float64)], 1
        )
        table = table[done_ids.to(table.device)]
        self._pending.append((keys, table))
        means = table[:, :-1].mean(0).tolist()
        extras["log"] = {f"/episode/{key}": m for key, m in zip(keys, means, strict=True)}
        for value in self._sums().values():
            value[done_ids] = 0

    def drain_episodes(self) -> list[dict]:
        """Pop the episodes finished since the last call (``{metric, "env_id"}``)."""
        finished: list[dict] = []
        for keys, table in self._pending:
            for row in table.tolist():
                record = dict(zip(keys, row, strict=False))
                record["env_id"] = int(row[-1])
                finished.append(record)
        self._pending = []
        return finished
