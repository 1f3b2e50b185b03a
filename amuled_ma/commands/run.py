"""``amuled run`` (the paper's main comparison) and ``amuled ablate`` (its ablations)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from amuled_ma.commands import _experiment as common


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled run`` and ``amuled ablate``."""
    run = subparsers.add_parser(
        "run",
        help="the paper's main comparison: base, base + shaping, human feedback, AMULED",
        description=(
            "Train base (c = 0) and shaped (c = 1) policies, fine-tune the base on human "
            "feedback and on AMULED's fused feedback, evaluate all four and write "
            "report.md. Resumable with --resume."
        ),
    )
    common.add_scenario_args(run)
    run.add_argument("--episodes", type=int, default=None, help="evaluation episodes per policy")
    run.set_defaults(handler=run_command)

    ablate = subparsers.add_parser(
        "ablate",
        help="the paper's ablations: clusters, aggregation, models, kl",
        description=(
            "Fine-tune the run's base policy with: each cluster alone and the unprompted "
            "moral agent (clusters); mean/max/vote vs bjs-dst (aggregation); every "
            "recording of the task or the scenario's model (models); a lambda_KL sweep (kl). "
            "Writes <run-dir>/ablate-<what>/ with a comparison table and plots."
        ),
    )
    common.add_scenario_args(ablate)
    ablate.add_argument(
        "--what",
        required=True,
        choices=("clusters", "aggregation", "models", "kl"),
        help="which ablation",
    )
    ablate.add_argument("--episodes", type=int, default=None, help="evaluation episodes")
    ablate.set_defaults(handler=ablate_command)


def run_command(args: argparse.Namespace) -> int:
    """Run ``amuled run``."""
    from amuled_ma.evaluate.evaluator import evaluate_run
    from amuled_ma.evaluate.report import write_report
    from amuled_ma.learn.experiments import MAIN_VARIANTS, write_config

    start = time.perf_counter()
    scenario = common.load(args)
    run_dir = common.run_dir_of(args, scenario)
    hint = common.command_line("run", args, run_dir)
    write_config(run_dir, scenario, {"variants": list(MAIN_VARIANTS)})
    common.say(f"run {scenario.name} -> {run_dir}")
    for variant in MAIN_VARIANTS:
        common.train_job(scenario, run_dir, variant, args, hint)
    results = evaluate_run(run_dir, scenario, episodes=args.episodes, progress=not args.no_progress)
    report = write_report(run_dir, results, title=f"{scenario.name}: the paper's main comparison")
    greedy = {k: v.get("greedy", {}).get("metrics", {}) for k, v in results["variants"].items()}
    common.say(_summary_line(scenario.task.name, greedy))
    common.say(
        f"run {scenario.name}: {len(MAIN_VARIANTS)} variants done in "
        f"{time.perf_counter() - start:.1f} s; report {report}"
    )
    return 0


def _summary_line(task: str, greedy: dict) -> str:
    from amuled_ma.evaluate.evaluator import PAPER_METRICS

    parts = []
    for name, metrics in greedy.items():
        cells = [
            f"{m}={metrics[m]['mean']:.2f}" for m in PAPER_METRICS.get(task, []) if m in metrics
        ]
        parts.append(f"{name}[{', '.join(cells)}]")
    return "  greedy: " + "; ".join(parts)


def ablate_command(args: argparse.Namespace) -> int:
    """Run ``amuled ablate``."""
    from amuled_ma.evaluate.evaluator import evaluate_run
    from amuled_ma.evaluate.report import plot_bars, write_report
    from amuled_ma.learn.experiments import ablation_variants, write_config

    start = time.perf_counter()
    scenario = common.load(args)
    run_dir = common.run_dir_of(args, scenario)
    out = run_dir / f"ablate-{args.what}"
    hint = common.command_line("ablate", args, run_dir, "--what", args.what)
    jobs = ablation_variants(args.what, scenario)
    write_config(out, scenario, {"ablation": args.what, "variants": [j[2] for j in jobs]})
    common.say(f"ablate {scenario.name} --what {args.what}: {len(jobs)} fine-tunes -> {out}")
    base_args = argparse.Namespace(**{**vars(args), "resume": True, "force": False})
    train_hint = common.command_line("train", args, run_dir)
    common.train_job(scenario, run_dir, "base", base_args, train_hint)
    for feedback, sc, folder in jobs:
        common.train_job(sc, run_dir, f"finetune:{feedback}", args, hint, out_dir=out / folder)
    results = evaluate_run(
        out,
        scenario,
        episodes=args.episodes,
        progress=not args.no_progress,
        extra_dirs=[run_dir / "base"],
    )
    report = write_report(out, results, title=f"{scenario.name}: ablation of {args.what}")
    plot_bars(results, "greedy", Path(out) / f"ablation_{args.what}.png")
    common.say(
        f"ablate {scenario.name} --what {args.what}: {len(jobs)} variants done in "
        f"{time.perf_counter() - start:.1f} s; report {report}"
    )
    return 0
