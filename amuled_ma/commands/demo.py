"""``amuled demo``: AMULED working on FindMilk (or Driving) in minutes, then a short live leg.

The comparison replays the authors' gpt-4o-mini recording with their recipe from their
published base (``scenarios/<task>-demo.toml``); the live leg asks a local Ollama model a few
states. The tiny model only exercises the live path: its moral judgement is not meaningful.
"""

from __future__ import annotations

import argparse
import os
import shlex
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.commands import _experiment as common
from amuled_ma.commands._demo_live import (
    PrefixWarmup,
    print_breakdown,
    read_report,
    start_warmup,
    write_live_leg,
)
from amuled_ma.commands._demo_live import say as _say
from amuled_ma.files.safe import write_text_atomic

if TYPE_CHECKING:
    from amuled_ma.scenario import (
        EvaluationConfig,
        FeedbackConfig,
        FinetuneConfig,
        PPOConfig,
        Scenario,
        TaskConfig,
    )
    from amuled_ma.servers.timing import CacheReuse, TimingLog

#: The demo's tasks; each runs the shipped scenario ``<task>-demo``
#: (``scenarios/<task>-demo.toml``, `demo_scenario`).
DEMO_TASKS: tuple[str, ...] = ("driving", "findmilk")

#: Request slots of the demo's private server (``OLLAMA_NUM_PARALLEL``). Each slot keeps
#: its own prefix cache, so each must evaluate the shared 3.6k-token prompt once; on a
#: 2-core machine one slot was faster than two (docs/ollama.md). The demo scenarios'
#: ``[feedback].concurrency`` is this: more requests in flight than slots would only queue.
DEMO_NUM_PARALLEL = 1


#: ``[feedback].concurrency`` on a server the demo did not start (``--host``,
#: ``$OLLAMA_HOST``, or a real model on the default install).
SHARED_SERVER_CONCURRENCY = 2


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled demo``."""
    parser = subparsers.add_parser(
        "demo",
        help="AMULED working on FindMilk in minutes (replayed beliefs), then a live leg",
        description=(
            "The paper's FindMilk comparison (base, base + shaping, human feedback, AMULED) "
            "with the moral clusters' beliefs replayed from the paper authors' recording and "
            "their recipe, fine-tuned from their published base (fetched once) at a "
            "demo-sized budget; report.md opens with every variant beside the paper's row; "
            "the viewer page view-episode0.html shows the AMULED fine-tune step by "
            "step. Then a short live leg: a few requests to a local Ollama model (a private "
            "one with the tiny model unless --host/--model), whose judgement is not "
            "meaningful; it shows the live path. For a real model: ollama pull "
            "llama3.1:8b, then --model llama3.1:8b."
        ),
    )
    parser.add_argument(
        "--task",
        choices=DEMO_TASKS,
        default="findmilk",
        help="task (default findmilk); its settings are scenarios/<task>-demo.toml",
    )
    parser.add_argument(
        "--model",
        default=None,
        help="Ollama model (default: amuled-tiny, registered on a private server)",
    )
    parser.add_argument(
        "--host",
        default=None,
        help="Ollama server URL (default: $OLLAMA_HOST if set; else a private server for "
        "amuled-tiny, http://127.0.0.1:11434 for any other model)",
    )
    parser.add_argument(
        "--run-dir", type=Path, default=None, help="run directory (default runs/demo-<task>)"
    )
    common.add_clusters_dir_argument(parser)
    common.add_overrides_argument(parser)  # applied after the demo scenario's own settings
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the run folder where it stopped (the demo always does; the option "
        "makes the resume command it prints on a stop work)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    common.add_offline_argument(parser)
    parser.set_defaults(handler=demo_command)


def demo_command(args: argparse.Namespace) -> int:
    """Run ``amuled demo``; return the exit code of the pipeline."""
    from amuled_ma.cli import FAILURES, report_failure
    from amuled_ma.experiments.pipeline import PipelineRequest
    from amuled_ma.learn.checkpoints import LAST
    from amuled_ma.servers import local_server as llm_server
    from amuled_ma.servers.hosts import DEFAULT_HOST, TINY_MODEL, preflight
    from amuled_ma.servers.timing import cache_reuse, record_timings

    start = time.perf_counter()
    fetch_inputs(args.task, offline=args.offline)
    model = args.model or TINY_MODEL
    host = args.host or os.environ.get("OLLAMA_HOST")
    if host is None and model != TINY_MODEL:
        host = DEFAULT_HOST  # a real model lives on the user's own Ollama install
    started_dir: Path | None = None
    server_log: Path | None = None  # the private server's debug log: prefix-cache reuse
    log_offset = 0
    if host is None:
        started_dir = llm_server.default_state_dir() / "demo"
        _say(f"starting a private Ollama server (state in {started_dir})")
        state, _ = llm_server.up(
            state_dir=started_dir,
            tiny=model == TINY_MODEL,
            timeout=120.0,
            num_parallel=DEMO_NUM_PARALLEL,
            extra_env={"OLLAMA_DEBUG": "1"},
        )
        host = state.host
        server_log = Path(state.log)
        log_offset = server_log.stat().st_size if server_log.is_file() else 0
    run_dir = args.run_dir or Path("runs") / f"demo-{args.task}"
    view: Path | None = None
    phases: list[tuple[str, TimingLog]] = []
    reuse: CacheReuse | None = None
    warmup: PrefixWarmup | None = None
    try:
        preflight(host, model)  # one clear error up front: no server or no model
        _say(f"beliefs from {model} at {host}")
        try:  # a failure from here on is the run's: reported, then the server stops
            scenario = demo_scenario(
                args.task,
                model=model,
                host=host,
                private=started_dir is not None,
                clusters_dirs=args.clusters_dir,
                overrides=args.overrides,
            )
            if started_dir is not None:  # our own idle server: evaluate the shared prompt now
                warmup = start_warmup(
                    host, model, scenario.task.name, scenario.feedback, scenario.resolve
                )
            with record_timings() as run_log:
                phases.append(("fine-tune", run_log))
                request = PipelineRequest(
                    scenario=scenario,
                    run_dir=run_dir,
                    resume=True,
                    progress=not args.no_progress,
                    hint=demo_hint(args, run_dir),
                    title=demo_title(
                        scenario.name, scenario.task.name, scenario.feedback, scenario.finetune
                    ),
                    offline=args.offline,
                )
                common.run_and_say(request)
            code = 0
        except FAILURES as error:
            code = report_failure(error, debug=getattr(args, "debug", False))
        if code == 0:
            imported = Path(scenario.output.runs_dir) / "authors" / scenario.task.name / "base"
            authors_base, base_results = None, None
            if scenario.finetune.recipe == "authors" and (imported / LAST).is_file():
                authors_base = imported
                base_results = evaluate_folder(
                    imported, scenario.ppo, scenario.task, scenario.evaluation
                )
            put_summary(
                run_dir,
                scenario.task.name,
                scenario.base.total_steps,
                scenario.finetune.iterations,
                authors_base,
                base_results,
            )
            with record_timings() as live_log:  # while the server still runs
                write_live_leg(run_dir, scenario, model=model, host=host)
            phases.append(("live leg", live_log))
            view = write_demo_view(run_dir)
        if server_log is not None:
            reuse = cache_reuse(server_log, log_offset)
    finally:
        if warmup is not None:
            warmup.join(5.0)  # long done when a run trained
            warmup.cut = warmup.is_alive()  # the server stops under it: not a failure
        if started_dir is not None:
            _say(llm_server.down(started_dir))
    if warmup is not None:
        _say(warmup.describe())
    print_breakdown(model, phases, reuse)
    _say(f"finished in {time.perf_counter() - start:.0f} s with exit code {code}")
    report = run_dir / "report.md"
    if code == 0 and report.is_file():
        print(report.resolve())
        if view is not None:
            print(view.resolve())
    return code


def demo_scenario(
    task: str,
    *,
    model: str,
    host: str,
    private: bool,
    clusters_dirs: Sequence[Path] = (),
    overrides: Sequence[str] = (),
) -> Scenario:
    """The scenario of a demo run: ``scenarios/<task>-demo.toml`` on the demo's server.

    Adds what the command line decides: the server, another model (with the Ollama options of
    ``scenarios/<task>.toml``), `SHARED_SERVER_CONCURRENCY` on a server the demo did not
    start; then ``--clusters-dir`` folders and ``--set`` overrides.

    Raises:
        ScenarioError: A bad override (the message names it).
    """
    from amuled_ma.scenario import load_scenario

    scenario = load_scenario(f"{task}-demo")
    changes: dict[str, object] = {"host": host}
    if model != scenario.feedback.model:
        changes["model"] = model
        changes["ollama"] = dict(load_scenario(task).feedback.ollama)
    if not private:
        changes["concurrency"] = SHARED_SERVER_CONCURRENCY
    scenario = scenario.replace("feedback", **changes)
    return common.customise(scenario, clusters_dirs=clusters_dirs, overrides=overrides)


def fetch_inputs(task: str, *, offline: bool = False) -> None:
    """Fetch the demo's recording and the authors' base it starts from when missing.

    Without the authors' base the fine-tunes start from the run's own (said on stderr).

    Raises:
        AmuledError: The recording is missing and cannot be fetched; the fixes named.
    """
    from amuled_ma.authors.download import (
        ensure_authors_base,
        ensure_recordings,
        replayed_recordings,
    )
    from amuled_ma.errors import AmuledError
    from amuled_ma.scenario import load_scenario

    scenario = load_scenario(f"{task}-demo")
    if scenario.feedback.source == "replay":
        ensure_recordings(
            scenario.resolve, replayed_recordings(scenario.feedback), offline=offline, say=_say
        )
        try:
            scenario.recording_path(required=True)
        except AmuledError:
            name = Path(scenario.feedback.recording).name
            raise AmuledError(
                f"amuled demo replays the paper authors' recording {name!r}, not found: set "
                "AMULED_RECORDINGS=FOLDER, or run 'amuled import authors PATH' (a clone of "
                "https://github.com/temetski/moral_agent)"
            ) from None
    if scenario.finetune.recipe == "authors":
        try:
            ensure_authors_base(
                task, runs=Path(scenario.output.runs_dir), offline=offline, say=_say
            )
        except AmuledError as error:
            _say(
                f"the fine-tunes start from this run's own base, not the authors' published one "
                f"(the figures will be further from the paper's): {error}"
            )


#: How the report's summary of every variant against the paper starts (`put_summary`).
SUMMARY_HEADING = "## Every variant beside the paper"
#: The paper's main comparison, in the order of its table.
MAIN_VARIANTS = ("base", "shaped", "finetune-human", "finetune-amuled")


def _cell(metrics: dict[str, Any], name: str) -> str:
    value = metrics[name]
    return f"{value['mean']:.2f} ± {value['half_width']:.2f}"


def summary_lines(
    task: str,
    base_steps: int,
    iterations: int,
    results: dict[str, Any],
    base: str | None,
    base_results: dict[str, Any] | None = None,
) -> list[str]:
    """The report's first section: each main variant, sampled, beside the paper's row.

    Per variant of `MAIN_VARIANTS` in ``results`` (``results.json``): its sampled paper
    metrics (mean ± 95% half-width), the paper's, and on FindMilk the greedy share that
    reaches the milk. ``base``: the folder the fine-tunes started from (None: the run's own);
    its `evaluate_folder` ``base_results``, when given, is the first row.
    """
    from amuled_ma.evaluate.paper import PAPER_COLUMNS, paper_row

    columns = PAPER_COLUMNS[task]
    names = " / ".join(c.replace("_", " ") for c in columns)
    start = (
        f"the paper authors' published base policy (`{base}`: their ppo.py, 500,000 steps, "
        "fetched from their repository)"
        if base
        else "this run's own base"
    )
    lines = [
        SUMMARY_HEADING,
        "",
        f"Demo-sized: {iterations:,} fine-tuning iterations (the paper: 1,000), one "
        f"training seed, {base_steps:,} steps for the run's own base and "
        f"shaped policies; the fine-tunes start from {start}. Sampled policy (the paper's "
        f"metric), {names}, mean ± 95% interval over the evaluation episodes:",
        "",
    ]
    rows = [(v, results.get("variants", {}).get(v), "") for v in MAIN_VARIANTS]
    if base and base_results:
        own = f"this run's own base, {base_steps:,} steps, the shaped policy's twin"
        rows[0] = ("base", rows[0][1], own)
        start_row = ("base", base_results, "the authors' published base the fine-tunes start from")
        rows.insert(0, start_row)
    for variant, found, words in rows:
        row = paper_row(task, variant)
        if not found or not found.get("sampled") or row is None:
            continue
        ours = " / ".join(_cell(found["sampled"]["metrics"], c) for c in columns)
        paper = " / ".join(f"{row.values[c]:g}" for c in columns)
        name = f"`{variant}`" if not words else f"`{variant}`: {words}"
        sentence = f"- **{row.label}** ({name}): {ours}; the paper {paper}"
        greedy = (found.get("greedy") or {}).get("metrics", {})
        if "reached_milk" in greedy:
            share = greedy["reached_milk"]["mean"]
            sentence += f"; reaches the milk in {share:.0%} of greedy episodes"
        lines.append(sentence + ".")
    return [*lines, ""]


def put_summary(
    run_dir: Path,
    task: str,
    base_steps: int,
    iterations: int,
    authors_base: Path | None,
    base_results: dict[str, Any] | None = None,
) -> None:
    """Put :func:`summary_lines` right under ``report.md``'s title (replacing an earlier one).

    Nothing without a report or results. ``authors_base``: the authors' base the fine-tunes
    started from (None: the run's own), ``base_results`` its `evaluate_folder`.

    Raises:
        AmuledError: As `read_report`.
    """
    import json

    text, results = read_report(run_dir), read_report(run_dir, "results.json")
    if text is None or results is None:
        return
    data = json.loads(results)
    base = str(authors_base) if authors_base is not None else None
    title, _, rest = text.partition("\n")
    if rest.lstrip("\n").startswith(SUMMARY_HEADING):  # a re-run: replace the old one
        rest = rest.lstrip("\n")
        rest = rest[rest.find("\n## ", 1) + 1 :] if "\n## " in rest else ""
    section = "\n".join(summary_lines(task, base_steps, iterations, data, base, base_results))
    write_text_atomic(run_dir / "report.md", f"{title}\n\n{section}\n{rest.lstrip(chr(10))}")


def evaluate_folder(
    folder: Path, ppo: PPOConfig, task: TaskConfig, ev: EvaluationConfig
) -> dict[str, Any]:
    """One policy folder's evaluation by the scenario's evaluator, as ``results.json`` holds it.

    Returns:
        ``{mode: {"metrics": {metric: {"mean", "half_width", ...}}}}``.

    Raises:
        CheckpointError: The checkpoint cannot be loaded (one line naming it).
    """
    from amuled_ma.evaluate.evaluator import run_episodes, summarize
    from amuled_ma.learn.checkpoints import LAST
    from amuled_ma.learn.policies import load_policy

    actor = load_policy(folder / LAST, ppo)
    entry: dict[str, Any] = {}
    for mode in ev.modes:
        records, _ = run_episodes(
            actor, task, episodes=ev.episodes, mode=mode, seed=ev.seed,
            record_trajectory=False,
        )  # fmt: skip
        entry[mode] = {"metrics": summarize(records, ev.confidence)}
    return entry


def demo_title(name: str, task: str, fb: FeedbackConfig, ft: FinetuneConfig) -> str:
    """The report's title: what the demo's run is, and that it is demo-sized."""
    where = (
        f"beliefs replayed from `{Path(fb.recording).name}`"
        if fb.source == "replay"
        else f"beliefs asked live of `{fb.model}`"
    )
    return (
        f"{name}: the paper's {task} comparison, demo-sized "
        f"({where}, {ft.recipe} recipe, {ft.iterations:,} fine-tuning iterations; "
        "the paper: 1,000)"
    )


def demo_hint(args: argparse.Namespace, run_dir: Path) -> str:
    """The command that continues this demo (printed with ``--resume`` when it stops)."""
    parts = ["amuled", "demo", "--task", args.task, "--run-dir", str(run_dir)]
    given = {"--model": [args.model], "--host": [args.host], "--clusters-dir": args.clusters_dir}
    for option, values in {**given, "--set": args.overrides}.items():
        parts += [word for value in values if value for word in (option, str(value))]
    return shlex.join(parts)


def write_demo_view(run_dir: Path) -> Path | None:
    """Write ``view-episode0.html`` of the AMULED fine-tune, linked from the report."""
    from amuled_ma.errors import AmuledError
    from amuled_ma.evaluate.report import link_viewer
    from amuled_ma.experiments.trained_variants import write_run_view

    _say("writing the step-by-step viewer of finetune-amuled")
    try:
        result = write_run_view(run_dir, ["finetune-amuled"], say=_say)
    except AmuledError as error:
        _say(f"no viewer written: {error}")
        return None
    link_viewer(run_dir)
    _say(f"viewer {result.path} ({result.size / 1e6:.2f} MB); open it in a browser")
    return result.path
