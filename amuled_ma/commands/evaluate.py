"""``amuled evaluate``: evaluate every trained variant of a run and write its report."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from amuled_ma.commands import _experiment as common
from amuled_ma.files.run_lock import run_folder_lock


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled evaluate``."""
    parser = subparsers.add_parser(
        "evaluate",
        help="evaluate a run's policies (mean and 95%% CI) and write report.md",
        description=(
            "Run N episodes of every trained variant in RUN_DIR, greedy and sampled, and "
            "write results.json, results.csv, report.md and PNG figures into RUN_DIR."
        ),
    )
    parser.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="a run directory")
    parser.add_argument(
        "--episodes",
        type=common.bounded_int(1),
        default=None,
        help="episodes per policy (default: scenario's, 50)",
    )
    parser.add_argument(
        "--modes",
        nargs="+",
        choices=("greedy", "sampled"),
        default=None,
        help="action selection modes (default: the scenario's)",
    )
    parser.add_argument(
        "--variants", nargs="+", default=None, help="only these variant folders (default: all)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    common.add_clusters_dir_argument(parser)
    parser.set_defaults(handler=evaluate_command)


def evaluate_command(args: argparse.Namespace) -> int:
    """Run ``amuled evaluate``."""
    from amuled_ma.experiments.run_folder import (
        read_record,
        scenario_of_run,
        shared_folders,
        variant_records,
    )

    start = time.perf_counter()
    run_dir = Path(args.run_dir)
    scenario = scenario_of_run(run_dir)  # a clear error when it is no run, before torch
    scenario = common.customise(scenario, clusters_dirs=args.clusters_dir)
    from amuled_ma.evaluate.evaluator import evaluate_run, variant_dirs  # torch, matplotlib
    from amuled_ma.evaluate.report import evaluation_outputs, write_report
    from amuled_ma.files.safe import check_write_targets

    check_write_targets(evaluation_outputs(run_dir))  # a link or a device: refused before work
    with run_folder_lock(run_dir):
        extra = None
        if run_dir.name.startswith("ablate-"):  # the run's folders the ablation shares
            extra = [run_dir.parent / name for name in shared_folders(run_dir)]
        records = variant_records([*variant_dirs(run_dir), *(extra or [])])
        results = evaluate_run(
            run_dir,
            scenario_name=scenario.name,
            task_config=scenario.task,
            evaluation=scenario.evaluation,
            ppo=scenario.ppo,
            episodes=args.episodes,
            modes=args.modes,
            variants=args.variants,
            progress=not args.no_progress,
            extra_dirs=extra,
            records=records,
        )
        report = write_report(run_dir, results, run=read_record(run_dir), records=records)
        common.say(
            f"evaluate {run_dir}: {len(results.variants)} variants x {results.episodes} "
            f"episodes in {time.perf_counter() - start:.1f} s; report {report}"
        )
        return 0
