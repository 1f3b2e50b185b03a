"""Steps per second of the task environments: batched torch core vs the Gymnasium view.

Random actions at ``--copies`` copies against a one-copy ``gymnasium.make`` loop; env-steps
per second, best of ``--repeats``, wall and CPU time on one thread. Targets: >= 1,000,000
env-steps/s per task at 4096 copies, and >= 20x the Gymnasium loop.
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path
from typing import Any

import numpy as np

from amuled_ma.bench._output import best_time, write_figures

TARGET_STEPS_PER_S = 1_000_000
TARGET_RATIO = 20.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options to ``parser``."""
    parser.add_argument(
        "--copies",
        default="1,64,1024,4096",
        help="comma-separated numbers of copies of the batched core (default: 1,64,1024,4096)",
    )
    parser.add_argument(
        "--tasks", default="findmilk,driving", help="comma-separated tasks (default: both)"
    )
    parser.add_argument(
        "--steps", type=int, default=200, help="steps per timed run of the batched core"
    )
    parser.add_argument(
        "--gym-steps", type=int, default=2000, help="steps per timed run of the Gymnasium loop"
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed runs (best is kept)")
    parser.add_argument("--layout", default="paper", help="FindMilk layout (paper or random)")
    parser.add_argument("--device", default="cpu", help="torch device of the batched core")
    parser.add_argument("--seed", type=int, default=0, help="seed of tasks and actions")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")


def _options(name: str, layout: str) -> dict[str, Any]:
    return {"layout": layout} if name == "findmilk" else {}


def bench_core(
    name: str, copies: int, steps: int, repeats: int, layout: str, device: str, seed: int
) -> dict[str, float]:
    """Time ``steps`` steps of the batched core with ``copies`` copies."""
    import torch  # here: `amuled --help` need not load it

    from amuled_ma.tasks import make_batched

    task = make_batched(name, copies, device=device, seed=seed, **_options(name, layout))
    task.reset()
    gen = torch.Generator().manual_seed(seed)
    actions = torch.randint(0, task.num_actions, (steps, copies), generator=gen).to(device)
    for i in range(min(steps, 20)):  # warm-up
        task.step(actions[i])

    def run() -> None:
        for i in range(steps):
            task.step(actions[i])
        if task.device.type == "cuda":
            torch.cuda.synchronize(task.device)

    _, wall, cpu = best_time(run, repeats)
    n = copies * steps
    return {"copies": copies, "steps_per_s": n / wall, "cpu_steps_per_s": n / max(cpu, 1e-9)}


def bench_gym(name: str, steps: int, repeats: int, layout: str, seed: int) -> dict[str, float]:
    """Time ``steps`` steps of the Gymnasium view in a Python loop."""
    import gymnasium as gym

    import amuled_ma  # noqa: F401  (registers the ids)
    from amuled_ma.tasks import get_task

    env = gym.make(get_task(name).gym_id, **_options(name, layout))
    env.reset(seed=seed)
    space = env.action_space
    if not isinstance(space, gym.spaces.Discrete):
        raise TypeError(f"{name}: expected a Discrete action space, got {space}")
    actions = np.random.default_rng(seed).integers(0, int(space.n), steps).tolist()

    def run() -> None:
        for a in actions:
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                env.reset()

    _, wall, cpu = best_time(run, repeats)
    return {"steps_per_s": steps / wall, "cpu_steps_per_s": steps / max(cpu, 1e-9)}


def main(args: argparse.Namespace) -> int:
    """Run the benchmark and print the figures; returns 0 (a benchmark, not a test)."""
    import torch  # here: `amuled --help` need not load it

    torch.set_num_threads(1)
    copies = [int(c) for c in str(args.copies).split(",") if c.strip()]
    tasks = [t.strip() for t in str(args.tasks).split(",") if t.strip()]
    print(
        f"amuled bench envs: torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"device {args.device}, python {platform.python_version()}, "
        f"best of {args.repeats} runs"
    )
    results: dict[str, Any] = {}
    for name in tasks:
        rows = [
            bench_core(name, c, args.steps, args.repeats, args.layout, args.device, args.seed)
            for c in copies
        ]
        loop = bench_gym(name, args.gym_steps, args.repeats, args.layout, args.seed)
        results[name] = {"batched": rows, "gym_loop": loop}
        label = f"{name} (layout {args.layout})" if name == "findmilk" else name
        print(f"\n{label}")
        print(f"  {'view':<22}{'env-steps/s':>14}{'(CPU time)':>14}{'x gym loop':>12}")
        base = loop["steps_per_s"]
        print(
            f"  {'gymnasium, 1 copy':<22}{loop['steps_per_s']:>14,.0f}"
            f"{loop['cpu_steps_per_s']:>14,.0f}{1.0:>12.1f}"
        )
        for row in rows:
            print(
                f"  {'batched, ' + str(row['copies']) + ' copies':<22}"
                f"{row['steps_per_s']:>14,.0f}{row['cpu_steps_per_s']:>14,.0f}"
                f"{row['steps_per_s'] / base:>12.1f}"
            )
        biggest = max(rows, key=lambda r: r["copies"])
        ok_rate = biggest["steps_per_s"] >= TARGET_STEPS_PER_S
        ok_ratio = biggest["steps_per_s"] / base >= TARGET_RATIO
        print(
            f"  target at {biggest['copies']} copies: >= {TARGET_STEPS_PER_S:,} env-steps/s "
            f"{'met' if ok_rate else 'MISSED'}, >= {TARGET_RATIO:.0f}x the loop "
            f"{'met' if ok_ratio else 'MISSED'}"
        )
    write_figures(args.json, results)
    return 0
