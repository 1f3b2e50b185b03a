"""``amuled demo``: AMULED working on FindMilk (or Driving) in minutes, then a short live leg.

**The comparison** (``scenarios/findmilk-demo.toml``): the paper's FindMilk comparison
(base, base + shaping, "human" feedback, AMULED) with the moral clusters' beliefs
**replayed** from the paper authors' own gpt-4o-mini recording, with their fine-tuning
recipe (``--recipe authors``), the fine-tunes starting from the authors' published base
policy (:func:`fetch_authors_base`), at a demo-sized budget chosen by measuring (300
fine-tuning iterations, one seed); ``report.md`` opens with every variant beside the
paper's row (:func:`put_summary`, :mod:`amuled_ma.evaluate.paper`), and the step-by-step
viewer of the AMULED fine-tune (``view-episode0.html``, as ``amuled view``) is written.
The recording is found by name (``$AMULED_RECORDINGS``, the user data folder of ``amuled
import authors``, or ``../shared/amuled-recordings`` beside the checkout); found nowhere, it
is fetched once from the authors' repository at a pinned commit, checked and converted
(:mod:`amuled_ma.authors.download`), before anything starts; with ``--offline`` (or no
network) the demo stops there with one line naming the manual route. ``--task
driving`` runs ``scenarios/driving-demo.toml``, the same on Driving (the AMULED reward from
their recorded fused beliefs, as ``scenarios/driving-authors.toml``).

**The live leg** (`amuled_ma.commands._demo_live`): a handful of real requests
(:data:`LIVE_STATES` states of the AMULED fine-tune's greedy episode x
:data:`LIVE_CLUSTERS`) to a local Ollama model through a belief store
(``RUN_DIR/live/beliefs.sqlite``), fused as in training; the answers are a labelled
section of ``report.md`` and ``live/live.json``. With no server given the demo starts a
private one (``amuled ollama up --tiny``) and stops it afterwards. The tiny model
(SmolLM2-135M) only exercises the live path: **its moral judgement is not meaningful**,
and the report says so. Point it at a real model with ``--model llama3.1:8b``.

What makes the live leg fast on a small CPU (``docs/ollama.md``, "Where a request's time
goes"): the private server runs one request slot (``OLLAMA_NUM_PARALLEL=1``: the shared
prompt is evaluated once, then reused from the server's prefix cache), the shared prompt is
evaluated while the policies train (:class:`PrefixWarmup`), and the tiny model answers with
the probabilities alone. At the end the demo prints where the live requests' time went
(:func:`print_breakdown`).

The demo adds only what depends on its command line (the server, another model, the
report's title) to its scenario and runs it through the same library function as
``amuled run``, :func:`amuled_ma.pipeline.run_pipeline`.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.commands import _experiment as common
from amuled_ma.commands._demo_live import (
    PrefixWarmup,
    print_breakdown,
    write_live_leg,
)
from amuled_ma.commands._demo_live import say as _say
from amuled_ma.safe_files import write_text_atomic

if TYPE_CHECKING:
    from amuled_ma.beliefs.timing import CacheReuse, TimingLog
    from amuled_ma.scenario import Scenario

#: The demo's tasks; each runs the shipped scenario ``<task>-demo``
#: (``scenarios/<task>-demo.toml``, :func:`demo_scenario`).
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
    from amuled_ma import llm_server
    from amuled_ma.beliefs.hosts import DEFAULT_HOST, TINY_MODEL, preflight
    from amuled_ma.beliefs.timing import cache_reuse, record_timings
    from amuled_ma.cli import FAILURES, report_failure
    from amuled_ma.errors import EXIT_REFUSED

    start = time.perf_counter()
    missing = missing_recording(args.task, offline=args.offline)
    if missing:  # an input refused, as every command's (not a usage error)
        print(f"amuled: error: {missing}", file=sys.stderr)
        return EXIT_REFUSED
    fetch_authors_base(args.task, offline=args.offline)
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
    debug = getattr(args, "debug", False)
    code = 1
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
        except FAILURES as error:
            code = report_failure(error, debug=debug)
        else:
            if started_dir is not None:  # our own idle server: evaluate the shared prompt now
                warmup = PrefixWarmup.start(host, model, scenario)
            with record_timings() as run_log:
                code = _run_pipeline(scenario, run_dir, demo_hint(args, run_dir), args, debug)
            if run_log.timings:
                phases.append(("fine-tune", run_log))
        if code == 0:
            put_summary(run_dir, scenario)
        if code == 0:  # while the server still runs
            with record_timings() as live_log:
                write_live_leg(run_dir, scenario, model=model, host=host)
            phases.append(("live leg", live_log))
            view = write_demo_view(run_dir)
        if server_log is not None:
            reuse = cache_reuse(server_log, log_offset)
    finally:
        if warmup is not None:
            warmup.join()
            warmup.cut = warmup.running()  # the server stops under it: not a failure
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

    The file holds every setting of the demo (its budget, the tiny model and its reply
    options, the private server's one request slot); this adds what the command line
    decides: the server (``[feedback].host``), another model (which keeps the Ollama
    options of the task's own scenario, ``scenarios/<task>.toml``: the file's are the
    tiny model's), :data:`SHARED_SERVER_CONCURRENCY` requests in flight on a server the
    demo did not start; then the user's ``--clusters-dir`` folders and ``--set`` overrides.

    Args:
        task: ``findmilk`` or ``driving``.
        model: The Ollama model asked.
        host: The server's URL.
        private: Whether the demo started that server (its one slot).
        clusters_dirs: ``--clusters-dir`` folders.
        overrides: ``--set SECTION.KEY=VALUE`` texts, applied last.

    Returns:
        The validated scenario.

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


def missing_recording(task: str, *, offline: bool = False) -> str | None:
    """One line when the demo's scenario replays a recording this machine lacks (else None).

    A pinned recording of the paper authors found nowhere here is first fetched and
    converted (:func:`amuled_ma.authors.download.ensure_recordings`, its lines said with
    ``[demo]``), unless ``offline`` or ``$AMULED_OFFLINE=1``.

    Args:
        task: ``findmilk`` or ``driving``.
        offline: Never fetch.

    Returns:
        The error line (a failed or refused fetch, or offline: the routes), or None.

    """
    from amuled_ma.authors.download import ensure_recordings, replayed_recordings
    from amuled_ma.errors import AmuledError
    from amuled_ma.scenario import load_scenario

    try:
        scenario = load_scenario(f"{task}-demo")
        if scenario.feedback.source != "replay":
            return None
        ensure_recordings(scenario, replayed_recordings(scenario), offline=offline, say=_say)
    except AmuledError as error:
        return str(error)
    try:
        scenario.recording_path(required=True)
    except AmuledError:
        name = Path(scenario.feedback.recording).name
        return (
            f"amuled demo replays the paper authors' recording {name!r}, not found: set "
            "AMULED_RECORDINGS=FOLDER, or run 'amuled import authors PATH' (a clone of "
            "https://github.com/temetski/moral_agent)"
        )
    return None


def fetch_authors_base(task: str, *, offline: bool = False) -> Path | None:
    """The authors' published base the demo's fine-tunes start from; fetched when missing.

    A ``recipe = "authors"`` demo scenario fine-tunes from the paper authors' published base
    policy, ``<runs_dir>/authors/<task>/base`` (where the pipeline finds it); missing, it is
    fetched from their repository and converted
    (:func:`amuled_ma.authors.download.ensure_authors_base`, its lines said with ``[demo]``).
    When it cannot be had (offline, no network, a refused download) the demo says why in
    one line and its fine-tunes start from the run's own base; the report says which.

    Args:
        task: ``findmilk`` or ``driving`` (a task without a pinned base: None).
        offline: Never fetch.

    Returns:
        The base folder, or None (the run's own base).

    """
    from amuled_ma.authors.download import ensure_authors_base
    from amuled_ma.errors import AmuledError
    from amuled_ma.scenario import load_scenario

    try:
        scenario = load_scenario(f"{task}-demo")
        if scenario.finetune.recipe != "authors":
            return None
        return ensure_authors_base(
            task, runs=Path(scenario.output.runs_dir), offline=offline, say=_say
        )
    except AmuledError as error:
        _say(
            f"the fine-tunes start from this run's own base, not the authors' published one "
            f"(the figures will be further from the paper's): {error}"
        )
        return None


#: How the report's summary of every variant against the paper starts (:func:`put_summary`).
SUMMARY_HEADING = "## Every variant beside the paper"
#: The paper's main comparison, in the order of its table.
MAIN_VARIANTS = ("base", "shaped", "finetune-human", "finetune-amuled")


def _cell(metrics: dict[str, Any], name: str) -> str:
    value = metrics[name]
    return f"{value['mean']:.2f} ± {value['half_width']:.2f}"


def summary_lines(
    scenario: Scenario,
    results: dict[str, Any],
    base: str | None,
    base_results: dict[str, Any] | None = None,
) -> list[str]:
    """The report's first section: each main variant, sampled, beside the paper's row.

    One sentence per variant of the paper's main comparison found in ``results``: its paper
    metrics (sampled policy, mean ± half-width of the 95% interval), the paper's figures,
    and on FindMilk the share of greedy episodes that reach the milk. When the fine-tunes
    started from the authors' published base, that base is the base row (``base_results``,
    measured by our evaluator) and the run's own base follows it, named as such.

    Args:
        scenario: The demo's scenario (its task and budget).
        results: ``results.json`` of the run.
        base: The folder the fine-tunes started from (None: the run's own base).
        base_results: That folder's evaluation (``{"sampled": ..., "greedy": ...}`` as a
            variant of ``results.json``); None: no base row of its own.

    Returns:
        The section's lines, its heading first.

    """
    from amuled_ma.evaluate.paper import PAPER_COLUMNS, paper_row

    task, ft = scenario.task.name, scenario.finetune
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
        f"Demo-sized: {ft.iterations:,} fine-tuning iterations (the paper: 1,000), one "
        f"training seed, {scenario.base.total_steps:,} steps for the run's own base and "
        f"shaped policies; the fine-tunes start from {start}. Sampled policy (the paper's "
        f"metric), {names}, mean ± 95% interval over the evaluation episodes:",
        "",
    ]
    rows = [(v, results.get("variants", {}).get(v), "") for v in MAIN_VARIANTS]
    if base and base_results:
        own = f"this run's own base, {scenario.base.total_steps:,} steps, the shaped policy's twin"
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


def put_summary(run_dir: Path, scenario: Scenario) -> None:
    """Put :func:`summary_lines` right under ``report.md``'s title (replacing an earlier one).

    Read and written as :func:`put_live_section` does; without a report or results, nothing
    is written.

    Raises:
        AmuledError: As :func:`put_live_section`.

    """
    import json

    from amuled_ma.evaluate.report.writing import MAX_REPORT_BYTES
    from amuled_ma.file_limits import read_bounded_bytes

    report, results = run_dir / "report.md", run_dir / "results.json"
    if not (report.is_file() and results.is_file()):
        return
    fix = f"is it the right folder? Write the report again with 'amuled evaluate {run_dir}'"
    text = read_bounded_bytes(report, MAX_REPORT_BYTES, "report", fix=fix).decode("utf-8")
    data = json.loads(read_bounded_bytes(results, MAX_REPORT_BYTES, "results", fix=fix))
    base, base_results = None, None
    if scenario.finetune.recipe == "authors":
        imported = Path(scenario.output.runs_dir) / "authors" / scenario.task.name / "base"
        if (imported / "model_last.pt").is_file():
            base, base_results = str(imported), evaluate_folder(imported, scenario)
    title, _, rest = text.partition("\n")
    if rest.lstrip("\n").startswith(SUMMARY_HEADING):  # a re-run: replace the old one
        rest = rest.lstrip("\n")
        rest = rest[rest.find("\n## ", 1) + 1 :] if "\n## " in rest else ""
    section = "\n".join(summary_lines(scenario, data, base, base_results))
    write_text_atomic(report, f"{title}\n\n{section}\n{rest.lstrip(chr(10))}")


def evaluate_folder(folder: Path, scenario: Scenario) -> dict[str, Any]:
    """One policy folder's evaluation, as a variant of ``results.json`` holds it.

    The scenario's evaluation (episodes, seed, confidence) in each of its modes, by the
    evaluator that wrote the run's results, so the rows compare like with like.

    Args:
        folder: A variant folder holding ``model_last.pt``.
        scenario: The run's scenario.

    Returns:
        ``{mode: {"metrics": {metric: {"mean", "half_width", ...}}}}``.

    Raises:
        CheckpointError: The checkpoint cannot be loaded (one line naming it).

    """
    from amuled_ma.evaluate.evaluator import run_episodes, summarize
    from amuled_ma.learn.checkpoints import LAST
    from amuled_ma.learn.policies import load_policy

    ev = scenario.evaluation
    actor = load_policy(folder / LAST, scenario)
    entry: dict[str, Any] = {}
    for mode in ev.modes:
        records, _ = run_episodes(
            actor, scenario, episodes=ev.episodes, mode=mode, seed=ev.seed,
            record_trajectory=False,
        )  # fmt: skip
        entry[mode] = {"metrics": summarize(records, ev.confidence)}
    return entry


def demo_title(scenario: Scenario) -> str:
    """The report's title: what the demo's run is, and that it is demo-sized."""
    fb, ft = scenario.feedback, scenario.finetune
    where = (
        f"beliefs replayed from `{Path(fb.recording).name}`"
        if fb.source == "replay"
        else f"beliefs asked live of `{fb.model}`"
    )
    return (
        f"{scenario.name}: the paper's {scenario.task.name} comparison, demo-sized "
        f"({where}, {ft.recipe} recipe, {ft.iterations:,} fine-tuning iterations; "
        "the paper: 1,000)"
    )


def demo_hint(args: argparse.Namespace, run_dir: Path) -> str:
    """The command that continues this demo (printed with ``--resume`` when it stops)."""
    parts = ["amuled", "demo", "--task", args.task, "--run-dir", str(run_dir)]
    if args.model:
        parts += ["--model", args.model]
    if args.host:
        parts += ["--host", args.host]
    for folder in args.clusters_dir:
        parts += ["--clusters-dir", str(folder)]
    for text in args.overrides:
        parts += ["--set", text]
    return shlex.join(parts)


def _run_pipeline(
    scenario: Scenario, run_dir: Path, hint: str, args: argparse.Namespace, debug: bool
) -> int:
    """Run the demo's main comparison through the pipeline; its exit code (failures printed)."""
    from amuled_ma import pipeline
    from amuled_ma.cli import FAILURES, report_failure

    request = pipeline.PipelineRequest(
        scenario=scenario,
        run_dir=run_dir,
        resume=True,
        progress=not args.no_progress,
        hint=hint,
        title=demo_title(scenario),
        offline=args.offline,
    )
    start = time.perf_counter()
    try:
        outcome = pipeline.run_pipeline(request, say=common.say)
    except FAILURES as error:
        return report_failure(error, debug=debug)
    common.say_outcome(request, outcome, time.perf_counter() - start)
    return 0


def write_demo_view(run_dir: Path) -> Path | None:
    """Write the viewer page of the demo's AMULED fine-tune and link it from the report.

    The page is ``RUN_DIR/view-episode0.html`` (:func:`amuled_ma.evaluate.viewer.write_view`,
    variant ``finetune-amuled``, greedy evaluation episode 0).

    Args:
        run_dir: The demo's run folder.

    Returns:
        The page's path, or None when it could not be written (the reason is printed).

    """
    from amuled_ma.errors import AmuledError
    from amuled_ma.evaluate.report import link_viewer
    from amuled_ma.evaluate.viewer import write_view
    from amuled_ma.experiments.trained_variants import run_to_view

    _say("writing the step-by-step viewer of finetune-amuled")
    try:
        view = run_to_view(run_dir, ["finetune-amuled"])
        result = write_view(run_dir, view.scenario, view.variants, episodes=view.episodes, say=_say)
    except AmuledError as error:
        _say(f"no viewer written: {error}")
        return None
    link_viewer(run_dir)
    _say(f"viewer {result.path} ({result.size / 1e6:.2f} MB); open it in a browser")
    return result.path
