"""``amuled demo``: the paper's main job end to end on a local LLM, with a demo-sized budget.

It trains the base and base + shaping policies briefly, fine-tunes the base on human
feedback and on AMULED's fused feedback with the five moral clusters asked **live** on a
local Ollama model, evaluates all four, writes ``report.md`` and ends with the step-by-step
viewer of the AMULED fine-tune (``view-episode0.html``, as ``amuled view``). With no server
given it starts a private one (``amuled ollama up --tiny``) and stops it afterwards. The tiny
model (SmolLM2-135M) only exercises the plumbing: its moral judgement is meaningless. Point
the demo at a real model with ``ollama pull llama3.1:8b`` and ``--model llama3.1:8b``.

Every belief comes from the live model, with the authors' prompts (3.6k tokens, of which all
but the state and the cluster's credence sentence are shared). What makes it fast on a small
CPU (``docs/ollama.md``, "Where a request's time goes"): the private server runs one request
slot (``OLLAMA_NUM_PARALLEL=1``: the shared prompt is evaluated once, then reused from the
server's prefix cache) without flash attention, and the tiny model answers with the
probabilities alone (no reasoning string, at most 128 tokens). At the end the demo prints
where the live requests' time went (:func:`print_breakdown`).

The demo's settings are a scenario file, ``scenarios/<task>-demo.toml`` (the task's shipped
scenario with a demo-sized budget and the tiny model's options); the demo adds only what
depends on its command line (the server, another model) and runs it through the same
library function as ``amuled run``, :func:`amuled_ma.pipeline.run_pipeline`.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from amuled_ma.commands import _experiment as common

if TYPE_CHECKING:
    from amuled_ma.beliefs.timing import CacheReuse, RequestTiming, TimingLog
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
        help="the main job end to end on a local Ollama model (demo-sized budget)",
        description=(
            "Train base and base + shaping policies briefly, fine-tune the base on human "
            "feedback and on AMULED's fused feedback with the five moral clusters asked live "
            "on a local Ollama model, evaluate all four, write report.md and the viewer page "
            "view-episode0.html (amuled view). With no server given, a private one is started "
            "(amuled ollama up --tiny) and stopped afterwards. "
            "The tiny model only exercises the plumbing; for a real model: ollama pull "
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
    parser.set_defaults(handler=demo_command)


def _say(message: str) -> None:
    print(f"[demo] {message}", file=sys.stderr, flush=True)


def demo_command(args: argparse.Namespace) -> int:
    """Run ``amuled demo``; return the exit code of the pipeline."""
    from amuled_ma import llm_server
    from amuled_ma.beliefs.hosts import DEFAULT_HOST, TINY_MODEL, preflight
    from amuled_ma.beliefs.timing import cache_reuse, record_timings
    from amuled_ma.cli import FAILURES, report_failure

    start = time.perf_counter()
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
            phases.append(("fine-tune", run_log))
        if code == 0:  # while the server still runs: the page may ask it about new states
            with record_timings() as view_log:
                view = write_demo_view(run_dir)
            phases.append(("viewer", view_log))
        if server_log is not None:
            reuse = cache_reuse(server_log, log_offset)
    finally:
        if warmup is not None:
            warmup.join()
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


class PrefixWarmup:
    """Evaluate the prompt prefix every request shares, on the private server, in the background.

    All the demo's prompts start with the same system prompt and few-shot turns (about
    3,300 of their 3,600 tokens); the server's first request must evaluate them (about
    40 s on one thread), the later ones find them in its prefix cache. This sends one
    chat with that prefix and an empty last user turn (one token generated, no belief)
    while the policies train, so the first belief request finds the prefix cached. The
    options that make Ollama reload a model (``num_ctx``...) are the run's, so the cache
    survives; with overrides that change the prompt the warm-up is merely wasted.

    Use :meth:`start`; the thread never raises (a failure is kept in :attr:`error`).

    Attributes:
        timing: Ollama's account of the warm-up (None until it is done, or on failure).
        error: Why it failed, if it did.

    """

    def __init__(self, host: str, model: str, messages: Sequence[tuple[str, str]], options: dict):
        self.host, self.model = host, model
        self.messages = [{"role": role, "content": text} for role, text in messages]
        self.options = options
        self.timing: RequestTiming | None = None
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name="amuled-warmup", daemon=True)

    @classmethod
    def start(cls, host: str, model: str, scenario: Scenario) -> PrefixWarmup | None:
        """Start the warm-up for the run the demo is about to make (None if it cannot).

        Args:
            host: The private server.
            model: The model the run asks.
            scenario: The run's scenario (its prompts and Ollama options).

        """
        from amuled_ma.beliefs.ollama import OllamaSource
        from amuled_ma.clusters import build_messages
        from amuled_ma.deliberation.plan import cluster_registry, panel_of
        from amuled_ma.errors import AmuledError

        try:  # the run reports any error itself
            registry = cluster_registry(scenario)
            clusters, _ = panel_of("amuled", scenario, registry)
            messages = build_messages(clusters[0], scenario.task.name, "", registry=registry)
            source = OllamaSource(model, host=host, **dict(scenario.feedback.ollama))
            source.close()
        except (AmuledError, ValueError, TypeError, IndexError) as error:
            _say(f"no prefix warm-up: {error}")
            return None
        options = {**source.options, "num_predict": 1}
        warmup = cls(host, model, [*messages[:-1], ("user", "")], options)
        warmup._thread.start()
        return warmup

    def _run(self) -> None:
        import ollama

        began = time.perf_counter()
        try:
            with ollama.Client(host=self.host, timeout=600.0) as client:
                reply = client.chat(model=self.model, messages=self.messages, options=self.options)
        except Exception as error:  # a warm-up failure only costs time
            self.error = f"{type(error).__name__}: {error}"
            return
        from amuled_ma.beliefs.timing import RequestTiming

        self.timing = RequestTiming.from_reply(reply, time.perf_counter() - began)

    def join(self, timeout: float = 5.0) -> None:
        """Wait a little for the warm-up (it is long done when the run ends)."""
        self._thread.join(timeout)

    def describe(self) -> str:
        """One line on what the warm-up did."""
        if self.timing is None:
            return f"prefix warm-up: {self.error or 'not finished'}"
        return (
            f"prefix warm-up while the policies trained: {self.timing.prompt_tokens:,} shared "
            f"prompt tokens (system prompt + few-shot turns) evaluated in "
            f"{self.timing.prefill_s:.1f} s (not a belief; its chat call is in the prefix "
            f"cache figures below)"
        )


def print_breakdown(
    model: str, phases: list[tuple[str, TimingLog]], reuse: CacheReuse | None
) -> None:
    """Print where the demo's live requests spent their time (Ollama's own metrics).

    Args:
        model: The model asked.
        phases: ``(name, log)`` of each phase that asked the model (the run's fine-tune,
            the viewer's states the run never asked).
        reuse: The private server's prefix-cache reuse (None: not our server).

    """
    from amuled_ma.beliefs.timing import timing_breakdown

    timings = [t for _, log in phases for t in log.timings]
    parts = [
        f"{name} {len(log.timings)} in {log.span_s:.1f} s" for name, log in phases if log.timings
    ]
    _say(f"live requests to {model}" + (f" ({', '.join(parts)})" if parts else "") + ":")
    wall = sum(log.span_s for _, log in phases)
    for line in timing_breakdown(timings, wall or None, reuse):
        _say(f"  {line}")
