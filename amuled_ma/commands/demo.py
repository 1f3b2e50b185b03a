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
probabilities alone (:data:`TINY_REPLY`: no reasoning string, at most 128 tokens). At the
end the demo prints where the live requests' time went (:func:`print_breakdown`).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from amuled_ma.commands._experiment import add_clusters_dir_argument, add_overrides_argument

if TYPE_CHECKING:
    from amuled_ma.beliefs.timing import CacheReuse, RequestTiming, TimingLog

#: Budget overrides: every ``--set`` the demo applies to the shipped scenario.
DEMO_BUDGET: dict[str, tuple[str, ...]] = {
    "findmilk": (
        "base.total_steps=65_536",  # greedy policy optimal after ~33k steps (bench train)
        "finetune.iterations=1",
        # 8 transitions (4 mini-batches of 2) from 4 copies x 2 steps: every copy starts
        # at the paper layout's start, so they share states: ~3 distinct states x 5
        # clusters asked live, instead of 8 x 5 with 1 copy x 8 steps (docs/ollama.md)
        "finetune.num_envs=4",
        "finetune.num_steps_per_env=2",
        "finetune.save_interval=1",
        "evaluation.episodes=10",
    ),
    "driving": (
        "base.total_steps=65_536",
        "finetune.iterations=1",
        "finetune.num_envs=4",
        "finetune.num_steps_per_env=2",
        "finetune.save_interval=1",
        "evaluation.episodes=10",
    ),
}

#: Overrides for the tiny model only (a real model keeps the scenario's options): the
#: probabilities alone, without the schema's reasoning string (the tiny model's is
#: meaningless), and a bound on the reply; about 40 tokens instead of about 110 per request.
TINY_REPLY: tuple[str, ...] = ("feedback.ollama={reasoning = false, num_predict = 128}",)

#: Request slots of the demo's private server (``OLLAMA_NUM_PARALLEL``). Each slot keeps
#: its own prefix cache, so each must evaluate the shared 3.6k-token prompt once; on a
#: 2-core machine one slot was faster than two (docs/ollama.md).
DEMO_NUM_PARALLEL = 1


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
        "--task", choices=sorted(DEMO_BUDGET), default="findmilk", help="task (default findmilk)"
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
    add_clusters_dir_argument(parser)
    add_overrides_argument(parser)  # applied after the demo budget
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.set_defaults(handler=demo_command)


def _say(message: str) -> None:
    print(f"[demo] {message}", file=sys.stderr, flush=True)


def demo_command(args: argparse.Namespace) -> int:
    """Run ``amuled demo``; return the exit code of the pipeline."""
    from amuled_ma import llm_server
    from amuled_ma.beliefs.hosts import DEFAULT_HOST, TINY_MODEL, preflight
    from amuled_ma.beliefs.timing import cache_reuse, record_timings
    from amuled_ma.cli import main

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
    overrides = [
        "feedback.source=ollama",
        f"feedback.model={model}",
        f"feedback.host={host}",
        # on the private server more requests in flight than slots would only queue
        f"feedback.concurrency={DEMO_NUM_PARALLEL if started_dir is not None else 2}",
        "feedback.timeout_s=600.0",
        *DEMO_BUDGET[args.task],
        *(TINY_REPLY if model == TINY_MODEL else ()),
        *args.overrides,
    ]
    argv = ["run", args.task, "--run-dir", str(run_dir), "--resume"]
    argv += [item for text in overrides for item in ("--set", text)]
    for folder in args.clusters_dir:
        argv += ["--clusters-dir", str(folder)]
    if args.no_progress:
        argv.append("--no-progress")
    view: Path | None = None
    phases: list[tuple[str, TimingLog]] = []
    reuse: CacheReuse | None = None
    warmup: PrefixWarmup | None = None
    try:
        preflight(host, model)  # one clear error up front: no server or no model
        _say(f"beliefs from {model} at {host}")
        if started_dir is not None:  # our own idle server: evaluate the shared prompt now
            warmup = PrefixWarmup.start(host, model, args.task, overrides, args.clusters_dir)
        with record_timings() as run_log:
            code = main(argv)
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

    _say("writing the step-by-step viewer of finetune-amuled")
    try:
        result = write_view(run_dir, variants=["finetune-amuled"], say=_say)
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
    def start(
        cls,
        host: str,
        model: str,
        task: str,
        overrides: Sequence[str],
        clusters_dirs: Sequence[Path] = (),
    ) -> PrefixWarmup | None:
        """Start the warm-up for the run the demo is about to make (None if it cannot).

        Args:
            host: The private server.
            model: The model the run asks.
            task: The demo's task.
            overrides: The run's ``--set`` overrides (they may change prompts or options).
            clusters_dirs: The run's ``--clusters-dir`` folders.

        """
        from amuled_ma.beliefs.ollama import OllamaSource
        from amuled_ma.clusters import build_messages
        from amuled_ma.commands._experiment import parse_override
        from amuled_ma.deliberation.feedback import cluster_registry, panel_of
        from amuled_ma.errors import AmuledError
        from amuled_ma.scenario import load_scenario

        try:  # the scenario as the run will see it (the run reports any error itself)
            scenario = load_scenario(task)
            if clusters_dirs:
                dirs = [str(Path(d).resolve()) for d in clusters_dirs]
                scenario = scenario.replace(
                    "feedback", clusters_dirs=[*scenario.feedback.clusters_dirs, *dirs]
                )
            for text in overrides:
                section, name, value = parse_override(text)
                scenario = scenario.replace(section, **{name: value})
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
