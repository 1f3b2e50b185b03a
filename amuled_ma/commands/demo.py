"""``amuled demo``: the paper's main job end to end on a local LLM, with a demo-sized budget.

It trains the base and base + shaping policies briefly, fine-tunes the base on human
feedback and on AMULED's fused feedback with the five moral clusters asked **live** on a
local Ollama model, evaluates all four, writes ``report.md`` and ends with the step-by-step
viewer of the AMULED fine-tune (``view-episode0.html``, as ``amuled view``). With no server
given it starts a private one (``amuled ollama up --tiny``) and stops it afterwards. The tiny
model (SmolLM2-135M) only exercises the plumbing: its moral judgement is meaningless. Point
the demo at a real model with ``ollama pull llama3.1:8b`` and ``--model llama3.1:8b``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from amuled_ma.commands._experiment import add_clusters_dir_argument, add_overrides_argument

#: Budget overrides: every ``--set`` the demo applies to the shipped scenario.
DEMO_BUDGET: dict[str, tuple[str, ...]] = {
    "findmilk": (
        "base.total_steps=65_536",  # greedy policy optimal after ~33k steps (bench train)
        "finetune.iterations=1",
        "finetune.num_envs=1",
        "finetune.num_steps_per_env=8",  # 8 transitions: at most 8 states x 5 clusters asked
        "finetune.save_interval=1",
        "evaluation.episodes=10",
    ),
    "driving": (
        "base.total_steps=65_536",
        "finetune.iterations=1",
        "finetune.num_envs=1",
        "finetune.num_steps_per_env=8",
        "finetune.save_interval=1",
        "evaluation.episodes=10",
    ),
}


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
    from amuled_ma.cli import main

    start = time.perf_counter()
    model = args.model or TINY_MODEL
    host = args.host or os.environ.get("OLLAMA_HOST")
    if host is None and model != TINY_MODEL:
        host = DEFAULT_HOST  # a real model lives on the user's own Ollama install
    started_dir: Path | None = None
    if host is None:
        started_dir = llm_server.default_state_dir() / "demo"
        _say(f"starting a private Ollama server (state in {started_dir})")
        state, _ = llm_server.up(state_dir=started_dir, tiny=model == TINY_MODEL, timeout=120.0)
        host = state.host
    run_dir = args.run_dir or Path("runs") / f"demo-{args.task}"
    overrides = [
        "feedback.source=ollama",
        f"feedback.model={model}",
        f"feedback.host={host}",
        "feedback.concurrency=2",
        "feedback.timeout_s=600.0",
        *DEMO_BUDGET[args.task],
        *args.overrides,
    ]
    argv = ["run", args.task, "--run-dir", str(run_dir), "--resume"]
    argv += [item for text in overrides for item in ("--set", text)]
    for folder in args.clusters_dir:
        argv += ["--clusters-dir", str(folder)]
    if args.no_progress:
        argv.append("--no-progress")
    view: Path | None = None
    try:
        preflight(host, model)  # one clear error up front: no server or no model
        _say(f"beliefs from {model} at {host}")
        code = main(argv)
        if code == 0:  # while the server still runs: the page may ask it about new states
            view = write_demo_view(run_dir)
    finally:
        if started_dir is not None:
            _say(llm_server.down(started_dir))
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
