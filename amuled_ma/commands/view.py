"""``amuled view``: one self-contained HTML page showing why a fine-tuned agent acts."""

from __future__ import annotations

import argparse
from pathlib import Path

from amuled_ma.commands import _experiment as common
from amuled_ma.errors import Terminated


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled view``."""
    parser = subparsers.add_parser(
        "view",
        help="write one HTML page replaying an evaluation episode step by step, with the "
        "panel's beliefs (works offline)",
        description=(
            "Replay evaluation episode K (seed [evaluation].seed + K) of each fine-tuned "
            "variant of RUN_DIR and write ONE self-contained HTML file (no server, no "
            "network): the task step by step, each panel agent's belief, fusion weight, "
            "status and reasoning, Dempster's conflict, the fused belief, the fine-tuned "
            "and the base policy's actions (flagged where they differ) and a timeline to "
            "jump to. Keys: ArrowLeft/ArrowRight, Home/End, PageUp/PageDown, [ and ]."
        ),
    )
    parser.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="a run directory")
    common.add_allow_plugin_argument(parser)  # a run folder names no code to run by itself
    parser.add_argument(
        "--variant",
        dest="variants",
        action="append",
        default=None,
        metavar="V",
        help="a variant folder to show (repeatable; default: every fine-tuned variant)",
    )
    common.add_episode_args(parser)
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        metavar="FILE",
        help="the HTML file (default: RUN_DIR/view-episode<K>.html); a new or a regular "
        "file, written whole or not at all: a link, a device or a FIFO is refused",
    )
    parser.add_argument(
        "--serve",
        action="store_true",
        help="also serve the page on 127.0.0.1 (a free port) until Ctrl-C; prints the URL",
    )
    parser.add_argument(
        "--port", type=common.bounded_int(0, 65535), default=0, help="port for --serve (0: free)"
    )
    parser.add_argument(
        "--serve-seconds",
        type=serve_seconds,
        default=None,
        metavar="S",
        help="with --serve, stop after S seconds (default: at Ctrl-C)",
    )
    parser.set_defaults(handler=view_command)


#: Longest ``--serve-seconds`` (about 115 days; Python's timers refuse far larger waits).
MAX_SERVE_SECONDS = 10_000_000


def serve_seconds(text: str) -> float:
    """An argparse ``type``: a finite number of seconds in (0, `MAX_SERVE_SECONDS`]."""
    value = common.positive_float(text)
    if value > MAX_SERVE_SECONDS:
        raise argparse.ArgumentTypeError(
            f"expected seconds in (0, {MAX_SERVE_SECONDS:,}], found {text}; leave it out to "
            "serve until Ctrl-C"
        )
    return value


def view_command(args: argparse.Namespace) -> int:
    """Run ``amuled view``.

    Raises:
        AmuledError: RUN_DIR is not a run folder; checked before torch is imported.
    """
    from amuled_ma.experiments.run_folder import scenario_of_run

    run_dir = Path(args.run_dir)
    scenario_of_run(run_dir)  # a missing or wrong folder: one line, before the heavy imports

    from amuled_ma.evaluate.page_server import serve
    from amuled_ma.experiments.trained_variants import write_run_view
    from amuled_ma.files.safe import check_write_target

    if args.output is not None:
        check_write_target(args.output)  # a link or a device is refused before any work
    result = write_run_view(
        run_dir,
        args.variants,
        args.episodes,
        args.output,
        episode=args.episode,
        mode=args.mode,
        say=common.say,
    )
    common.say(
        f"wrote {result.path} ({result.size / 1e6:.2f} MB, {len(result.variants)} variant(s), "
        f"{result.seconds:.1f} s); open it in a browser: {result.path.resolve().as_uri()}"
    )
    if args.serve:
        try:
            serve(result.path, port=args.port, seconds=args.serve_seconds, say=common.say)
        except KeyboardInterrupt as stop:
            if isinstance(stop, Terminated):
                raise  # SIGTERM: the usual exit status 143
            common.say("stopped serving")
    return 0
