"""Shared options and helpers of the experiment commands (train, finetune, run, ablate, ...)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from amuled_ma.scenario.overrides import parse_set

if TYPE_CHECKING:
    from collections.abc import Callable

    from amuled_ma.experiments.pipeline import PipelineRequest
    from amuled_ma.experiments.run_folder import Rerun
    from amuled_ma.scenario import Scenario


def bounded_int(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: an integer in ``[low, high]`` (``high`` None: no upper bound)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, found {text!r}") from None
        if value < low or (high is not None and value > high):
            wanted = f">= {low}" if high is None else f"in {low}..{high}"
            raise argparse.ArgumentTypeError(f"expected an integer {wanted}, found {value}")
        return value

    parse.__name__ = "integer"
    return parse


def positive_float(text: str) -> float:
    """An argparse ``type``: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, found {text!r}") from None
    if not (value > 0 and value != float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, found {text}")
    return value


def add_episode_args(parser: argparse.ArgumentParser, when: str = "") -> None:
    """Add ``--episode``, ``--episodes`` and ``--mode``: the evaluation episode replayed.

    ``when`` starts each help text (``"with --state-from: "``).
    """
    parser.add_argument(
        "--episode",
        type=bounded_int(0),
        default=0,
        metavar="K",
        help=f"{when}evaluation episode K, seeded [evaluation].seed + K (default 0)",
    )
    parser.add_argument(
        "--episodes",
        type=bounded_int(1),
        default=None,
        metavar="N",
        help=f"{when}the evaluation's episodes per policy, whose K-th is replayed (sampled "
        "draws depend on it; default: the run's results.json, else [evaluation].episodes)",
    )
    parser.add_argument(
        "--mode",
        choices=("greedy", "sampled"),
        default="greedy",
        help=f"{when}greedy: the policy's most probable action (default); sampled: drawn",
    )


def add_scenario_args(parser: argparse.ArgumentParser) -> None:
    """Add the scenario argument and the options every training command shares."""
    parser.add_argument(
        "scenario",
        metavar="SCENARIO",
        help="scenario TOML file, or the name of a shipped scenario (findmilk, driving)",
    )
    parser.add_argument(
        "--run-dir",
        type=Path,
        default=None,
        help="run directory (default: <[output].runs_dir>/<scenario name>)",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue unfinished variants from their last checkpoint, skip finished ones",
    )
    parser.add_argument(
        "--force", action="store_true", help="start over even where checkpoints exist"
    )
    parser.add_argument(
        "--seed", type=bounded_int(0, 2**63 - 1), default=None, help="override [task].seed"
    )
    add_clusters_dir_argument(parser)
    parser.add_argument(
        "--recipe",
        choices=("equation", "authors"),
        default=None,
        help="fine-tuning recipe: 'authors' runs a shipped scenario as its authors ran it "
        "(findmilk -> scenarios/findmilk-authors.toml: their KL term, run shape, synthetic "
        "human and evaluation); on another scenario it sets [finetune].recipe",
    )
    add_overrides_argument(parser)
    parser.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bars: a plain progress line at least every 30 s (log-friendly)",
    )


def add_offline_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--offline``: never fetch the paper authors' recordings (``$AMULED_OFFLINE=1`` too)."""
    parser.add_argument(
        "--offline",
        action="store_true",
        help="never fetch: a paper authors' recording found nowhere on this machine stops the "
        "run with the manual route (by default it is fetched once from their repository at a "
        "pinned commit, checked, and kept; docs/authors.md); also AMULED_OFFLINE=1",
    )


def add_clusters_dir_argument(parser: argparse.ArgumentParser) -> None:
    """Add the repeatable ``--clusters-dir DIR`` (user cluster files)."""
    parser.add_argument(
        "--clusters-dir",
        action="append",
        type=Path,
        default=[],
        metavar="DIR",
        help="a folder of your own cluster TOML files (repeatable; later ones win; a file "
        "overrides a shipped cluster of its name); adds to [feedback].clusters_dirs",
    )


def allow_plugin_path(text: str) -> str:
    """An argparse ``type``: a ``pkg.module:attr`` import path (``--allow-plugin``)."""
    from amuled_ma.clusters.plugins import IMPORT_PATH

    if not IMPORT_PATH.match(text):
        raise argparse.ArgumentTypeError(
            f"expected an import path pkg.module:attr (e.g. my_pkg.agents:MyAgent), found {text!r}"
        )
    return text


def add_allow_plugin_argument(parser: argparse.ArgumentParser) -> None:
    """Add the repeatable ``--allow-plugin pkg.module:attr`` (code a data file may name)."""
    parser.add_argument(
        "--allow-plugin",
        dest="allow_plugin",
        action="append",
        type=allow_plugin_path,
        default=[],
        metavar="PKG.MODULE:ATTR",
        help="let this run import and call this plug-in (an entry-point agent's name, a policy "
        "source's module, a rules source's policy), repeatable; a scenario, cluster file or "
        "run folder may name only installed amuled_ma.agents entry points without it",
    )


def add_overrides_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--set SECTION.KEY=VALUE`` and ``--allow-plugin`` (what this run changes)."""
    add_allow_plugin_argument(parser)
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a scenario key, value in TOML syntax (repeatable), "
        "e.g. --set finetune.lambda_kl=1.0 --set base.total_steps=100_000",
    )


def load(args: argparse.Namespace) -> Scenario:
    """Load the scenario named on the command line and apply ``--set`` overrides."""
    from amuled_ma.files.resources import scenarios_dir
    from amuled_ma.scenario import load_scenario

    name = str(args.scenario)
    recipe = getattr(args, "recipe", None)
    if recipe == "authors" and (scenarios_dir() / f"{name}-authors.toml").is_file():
        name = f"{name}-authors"  # the shipped scenario of the authors' procedure
    scenario = load_scenario(name)
    if recipe is not None and scenario.finetune.recipe != recipe:
        scenario = scenario.replace("finetune", recipe=recipe)
    return customise(
        scenario,
        clusters_dirs=getattr(args, "clusters_dir", []),
        overrides=getattr(args, "overrides", []),
    )


def customise(
    scenario: Scenario, *, clusters_dirs: Sequence[Path] = (), overrides: Sequence[str] = ()
) -> Scenario:
    """Apply ``--clusters-dir`` folders, then ``--set`` overrides, to a loaded scenario.

    ``clusters_dirs`` add to ``[feedback].clusters_dirs``; ``overrides`` apply in order.
    Prints a note for every user cluster file that overrides a cluster of its name.

    Raises:
        ScenarioError: An override of an unknown section or key, or a bad value.
    """
    user_dirs = [str(Path(d).resolve()) for d in clusters_dirs]
    if user_dirs:
        dirs = [*scenario.feedback.clusters_dirs, *user_dirs]
        scenario = scenario.replace("feedback", clusters_dirs=dirs)
    for text in overrides:
        section, name, value = parse_set(text)
        scenario = scenario.replace(section, **{name: value})
    if scenario.feedback.clusters_dirs:
        from amuled_ma.deliberation.plan import cluster_registry

        for o in cluster_registry(scenario.feedback, scenario.resolve).overridden:
            say(f"note: {o.new_path} overrides the cluster {o.name!r} of {o.old_path}")
    return scenario


#: ``--ray`` without an address: a local Ray started for the run.
LOCAL_RAY = "local"
#: ``(dest, option, default)`` of what a re-run repeats, in order; a list repeats its option,
#: a default is left out, ``--ray`` alone and ``--no-population`` are flags.
RERUN_OPTIONS: tuple[tuple[str, str, object], ...] = (
    ("recipe", "--recipe", None),
    ("clusters_dir", "--clusters-dir", None),
    ("overrides", "--set", None),
    ("allow_plugin", "--allow-plugin", None),  # a run folder never allows code by itself
    ("seed", "--seed", None),
    ("seeds", "--seeds", 1),
    ("jobs", "--jobs", 0),
    ("ray", "--ray", None),
    ("ray_resource", "--ray-resource", None),
    ("population", "--no-population", True),
    ("base", "--base", None),  # a fine-tune's only
)


def rerun_of(name: str, args: argparse.Namespace, *extra: str) -> Rerun:
    """The command that re-runs a job, as fields (``extra``: arguments before ``--run-dir``)."""
    from amuled_ma.experiments.run_folder import Rerun

    options: list[str] = []
    for dest, option, default in RERUN_OPTIONS:
        value = getattr(args, dest, default)
        if dest == "base" and name != "finetune":
            continue
        for one in value if isinstance(value, list) else [value]:
            if one != default:
                flag = one is False or one == LOCAL_RAY
                options += [option] if flag else [option, str(one)]
    name_option = getattr(args, "name", None) if name == "finetune" else None
    return Rerun(name, (str(args.scenario), *extra), tuple(options), name_option)


def say(message: str) -> None:
    """Print a status line (stderr stays free for errors)."""
    print(message, flush=True)


def run_and_say(request: PipelineRequest) -> None:
    """Run the pipeline of ``request``, then print its summary and the report's path."""
    from amuled_ma.experiments import pipeline

    start = time.perf_counter()
    outcome = pipeline.run_pipeline(request, say=say)
    name, task = request.scenario.name, request.scenario.task.name
    done = f"{len(outcome.seeds)} seed(s) done in {time.perf_counter() - start:.1f} s"
    if request.ablation is not None:
        say(
            f"ablate {name} --what {request.ablation}: {len(outcome.variants)} variants x "
            f"{done}; report {outcome.report}"
        )
        return
    from amuled_ma.evaluate.evaluator import PAPER_METRICS  # after the run: it imports torch

    parts = []  # the greedy means of the paper's metrics, per variant
    for variant, result in outcome.results.variants.items():
        metrics = result.greedy.metrics if result.greedy else {}
        means = [(m, metrics[m].mean) for m in PAPER_METRICS.get(task, []) if m in metrics]
        cells = [f"{m}={float('nan') if v is None else v:.2f}" for m, v in means]
        parts.append(f"{variant}[{', '.join(cells)}]")
    say("  greedy: " + "; ".join(parts))
    say(f"run {name}: {len(outcome.variants)} variants x {done}; report {outcome.report}")
