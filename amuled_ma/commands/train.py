"""``amuled train`` and ``amuled finetune``: train one variant of a scenario."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from amuled_ma.commands import _experiment as common
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import check_path_component


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled train`` and ``amuled finetune``."""
    train = subparsers.add_parser(
        "train",
        help="train a base policy (c = 0) or a base + shaping policy (c = 1)",
        description=(
            "Train a PPO policy on the task reward r = r_env + c * r_shaping: --variant base "
            "(c = 0, the policy fine-tunes start from) or shaped (c = [base].shaping_coef). "
            "Writes <run-dir>/<variant>/ with model_last.pt, curve.json, TensorBoard logs."
        ),
    )
    common.add_scenario_args(train)
    train.add_argument("--variant", choices=("base", "shaped"), default="base")
    train.set_defaults(handler=train_command)

    finetune = subparsers.add_parser(
        "finetune",
        help="fine-tune the base policy on fused moral feedback with a KL anchor",
        description=(
            "Fine-tune a copy of <run-dir>/base on r = f(B)[a] - lambda_KL * (log pi(a|s) - "
            "log pi_base(a|s)). Feedback: amuled (the clusters fused with bjs-dst), human "
            "(the authors' synthetic human: a demonstrator's action counts), human:rules (the "
            "task's rule-based synthetic human), cluster:<name> (one cluster), moral "
            "(unprompted moral agent), agg:<rule> (another fusion rule: mean, max, vote, mec, "
            "nash-vote, variance-vote, borda)."
        ),
    )
    common.add_scenario_args(finetune)
    finetune.add_argument(
        "--feedback",
        default="amuled",
        help="amuled | human | human:rules | moral | cluster:<name> | agg:<rule> (mean, max, "
        "vote, mec, nash-vote, variance-vote, borda) "
        "(default: amuled)",
    )
    finetune.add_argument(
        "--name",
        default=None,
        metavar="NAME",
        help="name this fine-tune (folder finetune-NAME), so that several panels live side "
        "by side in one run folder and one report; default: [feedback].name, else the "
        "feedback (finetune-amuled)",
    )
    finetune.add_argument(
        "--base",
        type=Path,
        default=None,
        metavar="FOLDER",
        help="the base policy's variant folder to fine-tune from and anchor to (default: "
        "<run-dir>/base), e.g. runs/authors/findmilk/base from 'amuled import authors'",
    )
    finetune.set_defaults(handler=train_command)


def train_command(args: argparse.Namespace) -> int:
    """Run ``amuled train`` or ``finetune``: a one-job request through the pipeline.

    The pipeline's preflight (every panel member can answer, the base exists) runs before
    any folder is made.
    """
    from amuled_ma.experiments.pipeline import PipelineRequest, train_alone

    scenario = common.load(args)
    run_dir = Path(args.run_dir) if args.run_dir else scenario.default_run_dir()
    start = time.perf_counter()
    base: Path | None = getattr(args, "base", None)
    if args.command == "train":
        variant, rerun = Variant.parse(args.variant), ("--variant", args.variant)
    else:
        if args.name is not None:
            scenario = scenario.replace("feedback", name=args.name)
        if scenario.feedback.name:
            check_path_component(scenario.feedback.name, "--name (or [feedback].name)")
        variant = Variant.finetune(args.feedback, label=scenario.feedback.name or None)
        rerun = ("--feedback", args.feedback)
    request = PipelineRequest(
        scenario,
        run_dir,
        rerun=common.rerun_of(args.command, args, *rerun),
        seed=args.seed,
        resume=args.resume,
        force=args.force,
        progress=not args.no_progress,
    )
    job = train_alone(
        request,
        variant,
        base_dir=base.parent if base else None,
        base_variant=base.name if base else "base",
        config={"variant": args.variant} if args.command == "train" else None,
    )
    shown = args.variant if args.command == "train" else job.out_dir.name
    common.say(
        f"{args.command} {scenario.name}/{shown}: done in "
        f"{time.perf_counter() - start:.1f} s; checkpoint {job.out_dir / 'model_last.pt'}"
    )
    return 0
