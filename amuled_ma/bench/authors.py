"""Time of a 1,000-iteration fine-tune with the authors' recipe, beside their ~6 minutes.

Trains a short base, then fine-tunes it as ``scenarios/<task>-authors.toml`` does (1 copy x
128 steps, 1,000 iterations, replayed gpt-4o-mini feedback) on one torch thread. Their
``finetune_moral.py`` took about 6 minutes (2.7-2.9 iterations/s) on this kind of machine.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from amuled_ma.bench._output import authors_scenario, output_folder

#: The authors' fine-tune time [s] (about 6 minutes, as in ``bench/train.py``'s reference).
AUTHORS_FINETUNE_S = 6 * 60.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options to ``parser``."""
    parser.add_argument(
        "--tasks", default="findmilk,driving", help="comma-separated tasks (default: both)"
    )
    parser.add_argument("--iterations", type=int, default=1000, help="fine-tune iterations")
    parser.add_argument(
        "--base-steps", type=int, default=51_200, help="env steps of the short base (51,200)"
    )
    parser.add_argument("--out", type=Path, default=None, help="keep the runs in this folder")


def main(args: argparse.Namespace) -> int:
    """Run the benchmark and print the figures; returns 0 (a benchmark, not a test)."""
    from amuled_ma.experiments.pipeline import PipelineRequest, train_alone
    from amuled_ma.records.variants import Variant

    rows = []
    with output_folder(args.out, "amuled-bench-authors-") as out:
        for task in [t.strip() for t in args.tasks.split(",") if t.strip()]:
            scenario = authors_scenario(task, args.base_steps)
            request = PipelineRequest(scenario, out / task, progress=False)
            train_alone(request, Variant("base"))
            start = time.perf_counter()
            job = train_alone(request, Variant.finetune("amuled"), iterations=args.iterations)
            seconds = time.perf_counter() - start
            assert job.outcome is not None
            rows.append((task, job.outcome.iterations, seconds))
    print(f"{'task':<10} {'iterations':>10} {'ours [s]':>9} {'authors [s]':>12} {'speed-up':>9}")
    for task, iterations, seconds in rows:
        scale = iterations / 1000
        authors = AUTHORS_FINETUNE_S * scale
        print(
            f"{task:<10} {iterations:>10,} {seconds:>9.1f} {authors:>12.0f} "
            f"{authors / seconds:>8.1f}x"
        )
    return 0
