"""``amuled run`` (the paper's main comparison) and ``amuled ablate`` (its ablations)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from amuled_ma.commands import _experiment as common
from amuled_ma.errors import AmuledError
from amuled_ma.run_lock import run_folder_lock


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
    run.add_argument(
        "--episodes",
        type=common.bounded_int(1),
        default=None,
        help="evaluation episodes per policy",
    )
    run.add_argument(
        "--base",
        type=Path,
        default=None,
        metavar="FOLDER",
        help="fine-tune every seed from this finished base folder instead of the run's own "
        "bases (default with --recipe authors: the authors' imported base, "
        "<runs_dir>/authors/<task>/base, when it is there)",
    )
    add_parallel_args(run)
    run.set_defaults(handler=run_command)

    ablate = subparsers.add_parser(
        "ablate",
        help="the paper's ablations: clusters, aggregation, models, kl; and budget",
        description=(
            "Fine-tune the run's base policy with: each cluster alone and the unprompted "
            "moral agent (clusters); mean/max/vote vs bjs-dst (aggregation); every "
            "recording of the task or the scenario's model (models); a lambda_KL sweep (kl); "
            "the panel asked about 100%, 30%, 10%, 3% of the distinct states, the rest "
            "answered by a distilled reward model, with uncertainty and random selection "
            "(budget, docs/distill.md). Writes <run-dir>/ablate-<what>/ with a comparison "
            "table and plots."
        ),
    )
    common.add_scenario_args(ablate)
    ablate.add_argument(
        "--what",
        required=True,
        choices=("clusters", "aggregation", "models", "kl", "budget"),
        help="which ablation",
    )
    ablate.add_argument(
        "--episodes", type=common.bounded_int(1), default=None, help="evaluation episodes"
    )
    add_parallel_args(ablate)
    ablate.set_defaults(handler=ablate_command)


#: ``--ray`` without an address: a local Ray started for the run.
LOCAL_RAY = "local"


def add_parallel_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--seeds`` (training replicas), ``--jobs`` and ``--ray`` (where jobs run)."""
    parser.add_argument(
        "--seeds",
        type=common.bounded_int(1),
        default=1,
        metavar="N",
        help="train every variant with N seeds (--seed or [task].seed, then +1, ...); "
        "replicas go to <variant>.seed<k>/ and the intervals cover the seeds (default: 1)",
    )
    parser.add_argument(
        "--jobs",
        type=common.bounded_int(0),
        default=0,
        metavar="N",
        help="train N jobs at once on a local Ray (one CPU each); 1 = all in this process, "
        "without Ray; 0 = one per CPU core, or 1 when the feedback is a live Ollama server "
        "(default: 0)",
    )
    parser.add_argument(
        "--ray",
        nargs="?",
        const=LOCAL_RAY,
        default=None,
        metavar="ADDRESS",
        help="train the jobs on Ray: alone, a local Ray with --jobs CPUs (even --jobs 1); "
        "with an address (HOST:PORT of 'ray start --head', or auto), on that cluster "
        "(docs/scale.md)",
    )
    parser.add_argument(
        "--ray-resource",
        default=None,
        metavar="NAME",
        help="each job needs one unit of this custom Ray resource: only nodes started with "
        "--resources '{\"NAME\": k}' train jobs, k at a time (keeps jobs off the GPU "
        "nodes that serve Ollama)",
    )


def _train_all(jobs: list, args: argparse.Namespace, hint: str) -> None:
    """Train a job graph with the command line's ``--jobs`` and print one line per job."""
    from amuled_ma.experiments.jobs import RayTarget, resolve_workers, run_jobs

    if args.ray_resource and args.ray is None:
        raise AmuledError("--ray-resource needs --ray: it names a resource of a Ray cluster")
    ray = None
    if args.ray is not None:
        ray = RayTarget(None if args.ray == LOCAL_RAY else args.ray, args.ray_resource)
    workers = resolve_workers(args.jobs, jobs)
    where = "" if ray is None else f" on Ray ({ray.address or 'local'})"
    common.say(f"  {len(jobs)} training jobs, {workers} at a time{where}")
    outcome = run_jobs(
        jobs,
        workers=workers,
        progress=not args.no_progress,
        hint=hint,
        describe=common.describe,
        ray=ray,
    )
    common.say(f"  training done in {outcome.wall_s:.1f} s on {outcome.workers} worker(s)")


def run_command(args: argparse.Namespace) -> int:
    """Run ``amuled run``."""
    from amuled_ma.evaluate.evaluator import evaluate_run
    from amuled_ma.evaluate.report import write_report
    from amuled_ma.experiments.plans import MAIN_VARIANTS, plan_run, training_seeds
    from amuled_ma.experiments.run_folder import write_config

    start = time.perf_counter()
    scenario = common.load(args)
    run_dir = common.run_dir_of(args, scenario)
    with run_folder_lock(run_dir):
        seeds = training_seeds(scenario, args.seed, args.seeds)
        hint = common.command_line("run", args, run_dir)
        base = args.base
        imported = Path(scenario.output.runs_dir) / "authors" / scenario.task.name / "base"
        if base is None and scenario.finetune.recipe == "authors":
            if (imported / "model_last.pt").is_file():
                base = imported
                common.say(f"  fine-tunes start from the authors' imported base {imported}")
            else:
                common.say(
                    f"  fine-tunes start from this run's own bases (no imported authors' base "
                    f"at {imported}; 'amuled import authors PATH' makes one)"
                )
        jobs = plan_run(scenario, run_dir, seeds, resume=args.resume, force=args.force, base=base)
        variants = [str(v) for v in MAIN_VARIANTS]
        write_config(run_dir, scenario, {"variants": variants, "seeds": seeds})
        common.say(f"run {scenario.name} -> {run_dir}")
        _train_all(jobs, args, hint)
        results = evaluate_run(
            run_dir, scenario, episodes=args.episodes, progress=not args.no_progress
        )
        report = write_report(
            run_dir, results, title=f"{scenario.name}: the paper's main comparison"
        )
        greedy = {k: v.get("greedy", {}).get("metrics", {}) for k, v in results["variants"].items()}
        common.say(_summary_line(scenario.task.name, greedy))
        common.say(
            f"run {scenario.name}: {len(MAIN_VARIANTS)} variants x {len(seeds)} seed(s) done in "
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
    from amuled_ma.evaluate.report import write_report
    from amuled_ma.experiments.plans import ablation_variants, plan_ablation, training_seeds
    from amuled_ma.experiments.run_folder import write_config

    start = time.perf_counter()
    scenario = common.load(args)
    run_dir = common.run_dir_of(args, scenario)
    with run_folder_lock(run_dir):
        out = run_dir / f"ablate-{args.what}"
        seeds = training_seeds(scenario, args.seed, args.seeds)
        hint = common.command_line("ablate", args, run_dir, "--what", args.what)
        variants = [variant.folder for variant, _ in ablation_variants(args.what, scenario)]
        jobs = plan_ablation(
            args.what, scenario, run_dir, seeds, resume=args.resume, force=args.force
        )
        # the run's folders an ablation evaluates with its own: the bases, and fine-tunes the
        # run already finished with the same settings (not trained again)
        shared = [job.out_dir.name for job in jobs if job.out_dir.parent == run_dir]
        write_config(
            out,
            scenario,
            {"ablation": args.what, "variants": variants, "seeds": seeds, "shared": shared},
        )
        common.say(
            f"ablate {scenario.name} --what {args.what}: {len(variants)} fine-tunes x "
            f"{len(seeds)} seed(s) -> {out}"
        )
        _train_all(jobs, args, hint)
        results = evaluate_run(
            out,
            scenario,
            episodes=args.episodes,
            progress=not args.no_progress,
            extra_dirs=[run_dir / name for name in shared],
        )
        report = write_report(
            out, results, title=f"{scenario.name}: ablation of {args.what}", ablation=args.what
        )
        common.say(
            f"ablate {scenario.name} --what {args.what}: {len(variants)} variants x "
            f"{len(seeds)} seed(s) done in "
            f"{time.perf_counter() - start:.1f} s; report {report}"
        )
        return 0
