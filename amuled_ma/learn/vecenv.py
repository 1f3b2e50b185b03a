"""The bridge from our batched task environments to rsl-rl's :class:`~rsl_rl.env.VecEnv`.

rsl-rl expects observations as a :class:`~tensordict.TensorDict` of observation
groups (we expose one group, ``"policy"``), ``dones`` as one tensor, truncations
under ``extras["time_outs"]`` (so PPO bootstraps the value of a timed-out state) and
metrics to log under ``extras["log"]`` with ``"/"``-prefixed keys. The task itself
auto-resets finished copies; this bridge only converts formats and keeps per-episode
book-keeping (return of the environment reward, length, task metrics) that the
trainer drains once per iteration for its learning curves.
"""

from __future__ import annotations

from typing import Any

import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

#: Name of the single observation group handed to rsl-rl.
OBS_GROUP = "policy"


def episode_records(info: dict[str, Any], done_ids: torch.Tensor, num_envs: int) -> list[dict]:
    """Turn a task's ``info["episode"]`` into one plain dict per finished episode.

    The task (:mod:`amuled_ma.tasks.base`) reports the episode accumulators of *every*
    copy, read before the reset, with a ``done`` mask; the rows of ``done_ids`` are the
    totals of the episodes that just ended.

    Args:
        info: The ``info`` dict of one task step.
        done_ids: Indices of the copies whose episode finished in this step.
        num_envs: Number of copies.

    Returns:
        One ``{metric: float}`` dict per finished copy, in ``done_ids`` order.

    """
    count = len(done_ids)
    episode = info.get("episode")
    if not episode or count == 0:
        return [{} for _ in range(count)]
    keys: list[str] = []
    columns: list[torch.Tensor] = []
    for key, value in episode.items():
        if key.startswith("_") or key == "done":
            continue
        tensor = torch.as_tensor(value).reshape(-1)
        if tensor.numel() != num_envs:
            continue
        keys.append(key)
        # float64 holds every float32, int (< 2**53) and bool value exactly
        columns.append(tensor.to(torch.float64))
    if not keys:
        return [{} for _ in range(count)]
    # one gather and one conversion to Python floats for all metrics of all episodes
    table = torch.stack(columns, 1)[done_ids.to(columns[0].device)].tolist()
    return [dict(zip(keys, row, strict=True)) for row in table]


class TaskVecEnv(VecEnv):
    """Expose a batched task (:mod:`amuled_ma.tasks`) as an rsl-rl ``VecEnv``.

    Args:
        task: A batched task instance (``reset``, ``step``, ``num_actions``, ...).
        max_episode_length: Step limit reported to rsl-rl (informational).
        cfg: Configuration recorded by rsl-rl's logger.

    """

    def __init__(self, task: Any, max_episode_length: int = 1000, cfg: dict | None = None) -> None:
        self.task = task
        self.num_envs = int(task.num_envs)
        self.num_actions = int(task.num_actions)
        self.device = torch.device(getattr(task, "device", "cpu"))
        self.max_episode_length = int(max_episode_length)
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.cfg = cfg or {}
        self._ep_return = torch.zeros(self.num_envs, device=self.device)
        self._ep_shaping = torch.zeros(self.num_envs, device=self.device)
        #: Finished episodes since the last :meth:`drain_episodes`.
        self.finished: list[dict] = []
        self.obs = self._as_float(task.reset())

    def _as_float(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(obs, device=self.device).float()

    def _as(self, value: Any, dtype: torch.dtype) -> torch.Tensor:
        """Return ``value`` as a ``dtype`` tensor on this device (itself when it already is)."""
        if isinstance(value, torch.Tensor) and value.dtype == dtype and value.device == self.device:
            return value
        return torch.as_tensor(value, device=self.device).to(dtype)

    def _wrap(self, obs: torch.Tensor) -> TensorDict:
        return TensorDict({OBS_GROUP: obs}, batch_size=[self.num_envs], device=self.device)

    def get_observations(self) -> TensorDict:
        """Return the current observations as a TensorDict with one ``"policy"`` group."""
        return self._wrap(self.obs)

    def reset(self) -> TensorDict:
        """Reset every copy and return the first observations."""
        self.obs = self._as_float(self.task.reset())
        self.episode_length_buf.zero_()
        self._ep_return.zero_()
        self._ep_shaping.zero_()
        return self._wrap(self.obs)

    @staticmethod
    def to_indices(actions: torch.Tensor) -> torch.Tensor:
        """Convert one-hot (or logit-like) rows to action indices; pass indices through."""
        if actions.dim() == 2:
            return actions.argmax(dim=-1)
        return actions.long()

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Step every copy with the given actions (one-hot rows or indices).

        Returns:
            Observations, rewards ``[N]``, dones ``[N]`` (terminated or truncated) and
            extras with ``time_outs``, ``log`` and the task's raw ``info``.

        """
        obs, reward, dones, extras = self.step_tensors(actions)
        return self._wrap(obs), reward, dones, extras

    def step_tensors(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        """:meth:`step` with the observations as a plain tensor ``[N, obs_dim]``."""
        index = self.to_indices(actions)
        if index.device != self.device:
            index = index.to(self.device)
        obs, reward, terminated, truncated, info = self.task.step(index)
        self.obs = self._as(obs, torch.float32)
        reward = self._as(reward, torch.float32)
        terminated = self._as(terminated, torch.bool)
        truncated = self._as(truncated, torch.bool)
        dones = terminated | truncated
        r_env = info.get("r_env")
        self._ep_return += reward if r_env is None else self._as(r_env, torch.float32)
        r_shaping = info.get("r_shaping")
        if r_shaping is not None:
            self._ep_shaping += self._as(r_shaping, torch.float32)
        self.episode_length_buf += 1
        extras: dict[str, Any] = {
            "time_outs": (truncated & ~terminated).float(),
            "info": info,
            "actions": index,
        }
        if bool(dones.any()):
            done_ids = dones.nonzero(as_tuple=False).squeeze(-1)
            records = episode_records(info, done_ids, self.num_envs)
            for record, env_id in zip(records, done_ids.tolist(), strict=True):
                # the task's own totals win; these are the bridge's, for tasks without them
                if "return_env" not in record:
                    record["return_env"] = float(self._ep_return[env_id])
                if "length" not in record:
                    record["length"] = float(self.episode_length_buf[env_id])
                if "return_shaping" not in record:
                    record["return_shaping"] = float(self._ep_shaping[env_id])
                record["env_id"] = env_id
            self.finished.extend(records)
            extras["log"] = {
                f"/episode/{key}": sum(r[key] for r in records if key in r)
                / max(1, sum(1 for r in records if key in r))
                for key in {k for r in records for k in r if k != "env_id"}
            }
            self._ep_return[done_ids] = 0.0
            self._ep_shaping[done_ids] = 0.0
            self.episode_length_buf[done_ids] = 0
        return self.obs, reward, dones.float(), extras

    def drain_episodes(self) -> list[dict]:
        """Return and forget the episodes finished since the last call."""
        finished, self.finished = self.finished, []
        return finished
