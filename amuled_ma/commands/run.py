"""``amuled run`` (the paper's main comparison) and ``amuled ablate`` (its ablations)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from amuled_ma.commands import _experiment as common
from amuled_ma.errors import AmuledError
from amuled_ma.scenario.overrides import parse_set

if TYPE_CHECKING:
    from amuled_ma.experiments.pipeline import PipelineRequest


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
    add_pipeline_args(run)
    run.add_argument(
        "--base",
        type=Path,
        default=None,
        metavar="FOLDER",
        help="fine-tune every seed from this finished base folder instead of the run's own "
        "bases (default with --recipe authors: the authors' imported base, "
        "<runs_dir>/authors/<task>/base, when it is there)",
    )

    ablate = subparsers.add_parser(
        "ablate",
        help="the paper's ablations: clusters, aggregation, models, kl; budget and weights",
        description=(
            "Fine-tune the run's base policy with: each cluster alone and the unprompted "
            "moral agent (clusters); mean/max/vote and the moral-uncertainty rules mec/"
            "nash-vote/variance-vote/borda vs bjs-dst (aggregation); every "
            "recording of the task or the scenario's model (models); a lambda_KL sweep (kl); "
            "the panel asked about 100%, 30%, 10%, 3% of the distinct states, the rest "
            "answered by a distilled reward model, with uncertainty and random selection "
            "(budget, docs/distill.md); the paper's fixed panel weights against weights learned "
            "from people, --weights FILE of 'amuled study fit-weights' (weights, "
            "docs/study.md). Writes <run-dir>/ablate-<what>/ with a comparison table and plots."
        ),
    )
    add_pipeline_args(ablate)
    ablate.add_argument(
        "--what",
        required=True,
        choices=("clusters", "aggregation", "models", "kl", "budget", "weights"),
        help="which ablation",
    )
    ablate.add_argument(
        "--weights",
        type=Path,
        default=None,
        metavar="FILE",
        help="panel weights learned from people ('amuled study fit-weights STUDY' writes "
        "STUDY/analysis/weights.json): sets [feedback].weights; --what weights compares them "
        "with the paper's fixed weights",
    )


#: The quick form's budget (``--quick``), ``(section, key): value``: about a minute for
#: ``amuled run findmilk`` on 2 cores (docs/reproduction.md, "The quick form"); a ``--set`` of
#: the same key wins.
QUICK_SETTINGS: dict[tuple[str, str], int] = {
    ("base", "total_steps"): 65_536,
    ("finetune", "iterations"): 50,
}
#: The quick form's evaluation episodes per policy and mode (``--episodes`` wins).
QUICK_EPISODES = 10
#: The quick form's run folder: the scenario's default with this ending (``--run-dir`` wins).
QUICK_SUFFIX = "-quick"


def add_pipeline_args(parser: argparse.ArgumentParser) -> None:
    """Add what ``run`` and ``ablate`` share: the scenario's, ``--quick``, the jobs' options."""
    common.add_scenario_args(parser)
    base, iterations = (
        QUICK_SETTINGS[("base", "total_steps")],
        QUICK_SETTINGS[("finetune", "iterations")],
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"the short form, about a minute: {base:,} base env steps, {iterations} "
        f"fine-tuning iterations, {QUICK_EPISODES} evaluation episodes, in "
        f"<runs_dir>/<scenario name>{QUICK_SUFFIX}; NOT the paper's length (500,000 / 1,000 "
        "/ 50), the output and report.md say so; --set and --episodes still win",
    )
    parser.add_argument(
        "--episodes",
        type=common.bounded_int(1),
        default=None,
        help="evaluation episodes per policy",
    )
    parser.add_argument(
        "--retrain",
        action="append",
        default=[],
        metavar="FOLDER",
        help="retrain this variant folder from scratch (e.g. finetune-amuled; its fine-tunes "
        "too if it is a base) and resume every other variant, then evaluate and report: "
        "the one command after a setting of one variant changed (repeatable)",
    )
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
        const=common.LOCAL_RAY,
        default=None,
        metavar="ADDRESS",
        help="train the jobs on Ray: alone, a local Ray with --jobs CPUs (even --jobs 1); "
        "with an address (HOST:PORT of 'ray start --head', or auto), on that cluster "
        "(docs/scale.md)",
    )
    parser.add_argument(
        "--no-population",
        dest="population",
        action="store_false",
        help="train every job alone; by default jobs of one task, network and run shape "
        "(e.g. the seeds and feedbacks of a sweep) train together as one batched "
        "population per core, each as it trains alone (docs/learning.md)",
    )
    parser.add_argument(
        "--ray-resource",
        default=None,
        metavar="NAME",
        help="each job needs one unit of this custom Ray resource: only nodes started with "
        "--resources '{\"NAME\": k}' train jobs, k at a time (keeps jobs off the GPU "
        "nodes that serve Ollama)",
    )
    common.add_offline_argument(parser)
    parser.set_defaults(handler=run_command)


def quick_note(base_steps: int, iterations: int, episodes: int) -> str:
    """The quick form's one-line warning, for the output and the report's title."""
    return (
        f"quick form: {base_steps:,} base env steps, "
        f"{iterations:,} fine-tuning iterations, {episodes} evaluation "
        "episodes; NOT the paper's length (500,000 / 1,000 / 50): a check that the pipeline "
        "runs, its figures are not the paper's"
    )


def request_of(args: argparse.Namespace) -> PipelineRequest:
    """The `PipelineRequest` of ``amuled run``, or of ``amuled ablate`` (``args.what`` set).

    Raises:
        AmuledError: ``--ray-resource`` without ``--ray``.
    """
    from amuled_ma.experiments.jobs import RayTarget
    from amuled_ma.experiments.pipeline import PipelineRequest

    if args.ray_resource and args.ray is None:
        raise AmuledError("--ray-resource needs --ray: it names a resource of a Ray cluster")
    scenario = common.load(args)
    command, extra = "run", []
    if getattr(args, "what", None) is not None:
        command, extra = "ablate", ["--what", args.what]
        if args.weights is not None:  # a path from this directory, as any file on the command line
            weights = str(args.weights.resolve())
            scenario = scenario.replace("feedback", weights=weights)
            extra += ["--weights", weights]
    run_dir = Path(args.run_dir) if args.run_dir else scenario.default_run_dir()
    episodes, title = args.episodes, None
    if args.quick:  # the quick budget but for the keys a --set names
        named = {parse_set(text)[:2] for text in args.overrides}
        quick = {key: value for key, value in QUICK_SETTINGS.items() if key not in named}
        scenario = scenario.changed(tuple((section, {k: v}) for (section, k), v in quick.items()))
        episodes = episodes or QUICK_EPISODES
        if args.run_dir is None:
            run_dir = run_dir.with_name(run_dir.name + QUICK_SUFFIX)
        what = f"ablation of {args.what}" if command == "ablate" else "the paper's main comparison"
        note = quick_note(scenario.base.total_steps, scenario.finetune.iterations, episodes)
        title = f"{scenario.name}: {what}, {note}"
        common.say(note)
        extra.append("--quick")
    ray = None
    if args.ray is not None:
        ray = RayTarget(None if args.ray == common.LOCAL_RAY else args.ray, args.ray_resource)
    return PipelineRequest(
        scenario=scenario,
        run_dir=run_dir,
        ablation=getattr(args, "what", None),
        seed=args.seed,
        seeds=args.seeds,
        episodes=episodes,
        base=getattr(args, "base", None),
        resume=args.resume,
        force=args.force,
        retrain=tuple(args.retrain),
        jobs=args.jobs,
        ray=ray,
        population=args.population,
        progress=not args.no_progress,
        rerun=common.rerun_of(command, args, *extra),
        title=title,
        offline=args.offline,
    )


def run_command(args: argparse.Namespace) -> int:
    """Run ``amuled run`` (the paper's main comparison) or, with ``--what``, ``amuled ablate``."""
    request = request_of(args)
    common.run_and_say(request)
    if args.quick:
        common.say(
            quick_note(
                request.scenario.base.total_steps,
                request.scenario.finetune.iterations,
                request.episodes or QUICK_EPISODES,
            )
        )
    return 0
