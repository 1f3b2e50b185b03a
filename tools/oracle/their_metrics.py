"""Evaluate CleanRL policies in the AMULED authors' own environments, as their notebook does.

    VENV/bin/python tools/oracle/their_metrics.py AUTHORS_CHECKOUT --task driving \
        MODEL.cleanrl_model [MODEL ...] [--episodes 50] [--json FILE]

Run with the oracle's virtualenv (their pins); imports their ``algorithms.ppo.Agent`` and
their environment from the checkout, edits nothing. Each policy plays ``--episodes``
episodes, episode ``i`` on ``env.reset(seed=42 + i)``, actions sampled from the policy
(``Agent.get_action_and_value``, torch seeded 42 once per policy), the environment made as
in ``notebooks/data_plots.ipynb`` cells 1-4 (``gym.make(env_id, validate=True)``, then
``FlattenObservation``). Reported per policy: the mean of their ``env.log()`` metrics at the
episode's end (FindMilk: steps to milk, crying babies passed, sleeping babies passed;
Driving: car collisions, lane changes, grandmas rescued), and for Driving also the number
of steps whose lane actually changed: their ``lane changes`` counts ``action != 0``
(``environments/drive.py:136``), which includes a move against the road's edge that
``clip`` leaves in the same lane (``drive.py:79-80, 90-93``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ENV_IDS = {"findmilk": "environments.milk:FindMilk-v4", "driving": "environments.drive:Driving"}


def main() -> int:
    """Evaluate every policy given; print one line each and optionally write JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("authors", type=Path)
    ap.add_argument("models", type=Path, nargs="+")
    ap.add_argument("--task", default="findmilk", choices=sorted(ENV_IDS))
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    sys.path.insert(0, str(args.authors.resolve()))
    os.environ.setdefault("CUDA_VISIBLE_DEVICES", "")
    import gymnasium as gym
    import numpy as np
    import torch
    from algorithms.ppo import Agent

    torch.set_num_threads(1)
    env = gym.wrappers.FlattenObservation(gym.make(ENV_IDS[args.task], validate=True))
    env.single_action_space = env.action_space  # their notebook's stand-in for SyncVectorEnv
    env.single_observation_space = env.observation_space
    out: dict[str, dict[str, float]] = {}
    for path in args.models:
        agent = Agent(env)
        agent.load_state_dict(torch.load(path, map_location="cpu"))
        torch.manual_seed(42)
        totals: dict[str, list[float]] = {}
        for i in range(args.episodes):
            obs, _ = env.reset(seed=42 + i)
            done, steps, moved = False, 0, 0
            while not done:
                lane = env.unwrapped.lane if args.task == "driving" else None
                with torch.no_grad():
                    action, _, _, _ = agent.get_action_and_value(torch.Tensor(obs))
                obs, _, terminated, truncated, _ = env.step(action.numpy())
                done = bool(np.logical_or(terminated, truncated))
                steps += 1
                if lane is not None:
                    moved += int(env.unwrapped.lane != lane)
            log = env.unwrapped.log()
            row = {log["main_goal"][0]: float(log["main_goal"][1])}
            row.update({log[k][0]: float(log[k][1]) for k in ("metric1", "metric2")})
            row["episode length"] = float(steps)
            if args.task == "driving":
                row["lanes actually changed"] = float(moved)
            for k, v in row.items():
                totals.setdefault(k, []).append(v)
        means = {k: round(float(np.mean(v)), 3) for k, v in totals.items()}
        out[str(path)] = means
        print(path, json.dumps(means), flush=True)
    if args.json:
        args.json.write_text(
            json.dumps({"task": args.task, "episodes": args.episodes, "policies": out}, indent=1)
            + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
