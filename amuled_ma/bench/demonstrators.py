"""Time of the authors' synthetic human demonstrators and the distinct states they meet.

FindMilk's rule demonstrator (1,000 episodes) and Driving's Q-learning one (10,000, counted
from episode 601) on one torch thread, best of ``--repeats``, beside the authors' notebook
(1,120 FindMilk and 12,270 Driving states). Target: Driving in under 60 s.
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path
from typing import Any

from amuled_ma.bench._output import best_time, write_figures

TARGET_DRIVING_S = 60.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options to ``parser``."""
    parser.add_argument("--seed", type=int, default=0, help="demonstrator seed (default 0)")
    parser.add_argument(
        "--findmilk-episodes", type=int, default=1000, help="FindMilk episodes (default 1000)"
    )
    parser.add_argument(
        "--driving-episodes", type=int, default=10_000, help="Driving episodes (default 10000)"
    )
    parser.add_argument(
        "--batch-size",
        type=int,
        default=2500,
        help="Driving episodes played side by side (default 2500; the counts do not change)",
    )
    parser.add_argument(
        "--tasks", default="findmilk,driving", help="comma-separated tasks (default: both)"
    )
    parser.add_argument("--repeats", type=int, default=1, help="timed runs (best is kept)")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")


def main(args: argparse.Namespace) -> int:
    """Run the benchmark and print the figures; returns 0 (a benchmark, not a test)."""
    import torch  # here: `amuled --help` need not load it

    from amuled_ma.tasks.demonstrators import (
        AUTHORS_STATE_COUNTS,
        DRIVING_COUNT_FROM,
        play_driving,
        play_findmilk,
    )

    torch.set_num_threads(1)
    tasks = [t.strip() for t in str(args.tasks).split(",") if t.strip()]
    print(
        f"amuled bench demonstrators: torch {torch.__version__}, threads "
        f"{torch.get_num_threads()}, python {platform.python_version()}, seed {args.seed}, "
        f"best of {args.repeats} run(s)"
    )
    rows: dict[str, dict[str, Any]] = {}
    episodes = {"findmilk": args.findmilk_episodes, "driving": args.driving_episodes}
    play = {
        "findmilk": lambda: play_findmilk(seed=args.seed, episodes=args.findmilk_episodes),
        "driving": lambda: play_driving(
            seed=args.seed, episodes=args.driving_episodes, batch_size=args.batch_size
        ),
    }
    for name in tasks:
        if name not in play:
            print(f"unknown task {name!r}: expected findmilk or driving")
            return 2
        played = episodes[name] - (DRIVING_COUNT_FROM if name == "driving" else 0)
        table, wall, cpu = best_time(play[name], args.repeats)
        rows[name] = {
            "episodes": episodes[name],
            "episodes_played": max(played, 0),
            "seconds": wall,
            "cpu_seconds": cpu,
            "pairs_counted": int(table.counts.sum()),
            "states": table.num_states,
            "authors_states": AUTHORS_STATE_COUNTS[name],
        }
    print(
        f"\n  {'task':<10}{'episodes':>10}{'played':>8}{'seconds':>9}{'(CPU)':>8}"
        f"{'pairs':>11}{'states':>8}{'authors':>9}"
    )
    for name, r in rows.items():
        print(
            f"  {name:<10}{r['episodes']:>10,}{r['episodes_played']:>8,}{r['seconds']:>9.1f}"
            f"{r['cpu_seconds']:>8.1f}{r['pairs_counted']:>11,}{r['states']:>8,}"
            f"{r['authors_states']:>9,}"
        )
    if "driving" in rows and args.driving_episodes == 10_000:
        ok = rows["driving"]["seconds"] < TARGET_DRIVING_S
        print(
            f"  target: Driving 10,000 episodes in < {TARGET_DRIVING_S:.0f} s "
            f"{'met' if ok else 'MISSED'}"
        )
    write_figures(args.json, rows)
    return 0
