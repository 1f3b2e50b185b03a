"""A tiny batched task with the amuled_ma.tasks interface, for learner tests."""

from __future__ import annotations

import numpy as np
import torch


class GridTask:
    """Walk on a 5x5 grid from (0, 0) to (4, 4); a 'baby' cell (2, 0) gives shaping reward.

    Actions: 0 up, 1 down, 2 left, 3 right. Reward -0.1 per step, +1 at the goal.
    """

    action_names = ("up", "down", "left", "right")
    num_actions = 4
    obs_dim = 4
    SIZE = 5

    def __init__(
        self, num_envs, *, device="cpu", seed=0, shaping_coef=0.0, max_steps=30, **options
    ):
        self.num_envs = num_envs
        self.device = torch.device(device)
        self.shaping_coef = shaping_coef
        self.max_steps = max_steps
        self.rng = np.random.default_rng(seed)
        self.pos = torch.zeros(num_envs, 2, dtype=torch.long)
        self.t = torch.zeros(num_envs, dtype=torch.long)
        self.visited = torch.zeros(num_envs, dtype=torch.bool)

    def _obs(self):
        goal = torch.full((self.num_envs, 2), self.SIZE - 1)
        return torch.cat([self.pos, goal], dim=1).float()

    def reset(self):
        self.pos.zero_()
        self.t.zero_()
        self.visited.zero_()
        return self._obs()

    def prompt_variables(self, env_ids):
        return [{"x": int(self.pos[i, 0]), "y": int(self.pos[i, 1])} for i in env_ids]

    def step(self, actions):
        actions = torch.as_tensor(actions).long()
        delta = torch.tensor([[0, 1], [0, -1], [-1, 0], [1, 0]])[actions]
        self.pos = (self.pos + delta).clamp(0, self.SIZE - 1)
        self.t += 1
        at_baby = (self.pos[:, 0] == 2) & (self.pos[:, 1] == 0) & ~self.visited
        self.visited |= at_baby
        terminated = (self.pos == self.SIZE - 1).all(dim=1)
        truncated = (self.t >= self.max_steps) & ~terminated
        r_env = -0.1 + terminated.float()
        r_shaping = at_baby.float()
        reward = r_env + self.shaping_coef * r_shaping
        done = terminated | truncated
        final_obs = self._obs()
        info = {"r_env": r_env, "r_shaping": r_shaping, "final_obs": final_obs}
        # as amuled_ma.tasks.base: accumulators of every copy, read before the reset
        info["episode"] = {
            "done": done.clone(),
            "steps_to_milk": self.t.clone(),
            "reached_milk": terminated.clone(),
            "crying_pacified": self.visited.long(),
        }
        if done.any():
            ids = done.nonzero().squeeze(-1)
            self.pos[ids] = 0
            self.t[ids] = 0
            self.visited[ids] = False
        return self._obs(), reward, terminated, truncated, info


def grid_factory(scenario, num_envs, *, shaping_coef, seed):
    return GridTask(num_envs, seed=seed, shaping_coef=shaping_coef)
