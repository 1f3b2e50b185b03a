"""``amuled ollama up|down|status``: a private local Ollama server for experiments and tests."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from amuled_ma.commands._experiment import bounded_int, positive_float
from amuled_ma.servers import local_server as llm_server


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled ollama`` and its ``up``, ``down`` and ``status`` sub-commands."""
    parser = subparsers.add_parser(
        "ollama",
        help="start, stop or inspect a private local Ollama server",
        description=(
            "Run a private Ollama server on a free 127.0.0.1 port with its own model directory, "
            "so experiments never touch your own Ollama install. 'up' prints the server's URL "
            "on stdout (use it as OLLAMA_HOST); 'down' stops only the server 'up' started."
        ),
    )
    actions = parser.add_subparsers(dest="ollama_action", metavar="ACTION")
    home = str(llm_server.default_state_dir()).replace(str(Path.home()), "~", 1)
    state_help = f"directory for the server's state, models and log (default {home})"

    up = actions.add_parser(
        "up",
        help="start the server (or reuse the running one) and print its URL",
        description=(
            "Start 'ollama serve' in the background and print its URL. The binary is --binary, "
            "$AMULED_OLLAMA_BIN, 'ollama' on PATH, or the copy built by .ci/setup-ollama."
        ),
    )
    up.add_argument("--binary", type=Path, help="the ollama executable to run")
    up.add_argument(
        "--tiny",
        action="store_true",
        help=f"register '{llm_server.TINY_MODEL}' (SmolLM2-135M-Instruct, for plumbing tests)",
    )
    up.add_argument("--gguf", type=Path, help="GGUF file for --tiny (default: found automatically)")
    up.add_argument(
        "--port", type=bounded_int(1, 65535), help="port on 127.0.0.1 (default: a free one)"
    )
    up.add_argument(
        "--num-parallel", type=bounded_int(1), default=2, help="OLLAMA_NUM_PARALLEL (default 2)"
    )
    up.add_argument(
        "--timeout", type=positive_float, default=60.0, help="seconds to wait for the server"
    )
    up.add_argument("--state-dir", type=Path, help=state_help)
    up.set_defaults(handler=_up)

    down = actions.add_parser("down", help="stop the server that 'up' started")
    down.add_argument("--state-dir", type=Path, help=state_help)
    down.set_defaults(handler=_down)

    stat = actions.add_parser("status", help="show the recorded server and whether it answers")
    stat.add_argument("--state-dir", type=Path, help=state_help)
    stat.add_argument("--json", action="store_true", help="print the status as JSON")
    stat.set_defaults(handler=_status)

    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def _up(args: argparse.Namespace) -> int:
    if args.tiny:
        print("[ollama] starting the server and registering the tiny model", file=sys.stderr)
    state, started = llm_server.up(
        binary=args.binary,
        state_dir=args.state_dir,
        port=args.port,
        tiny=args.tiny,
        gguf=args.gguf,
        num_parallel=args.num_parallel,
        timeout=args.timeout,
    )
    verb = "started" if started else "already running:"
    models = ", ".join(state.models) or "none registered"
    print(
        f"[ollama] {verb} ollama {state.version} pid {state.pid} at {state.host} "
        f"(models: {models}; log: {state.log})",
        file=sys.stderr,
    )
    print(f"[ollama] use it: export OLLAMA_HOST={state.host}", file=sys.stderr)
    print(state.host)
    return 0


def _down(args: argparse.Namespace) -> int:
    print(f"[ollama] {llm_server.down(args.state_dir)}")
    return 0


def _status(args: argparse.Namespace) -> int:
    info = llm_server.status(args.state_dir)
    if args.json:
        print(json.dumps(info, indent=2))
    elif not info["running"]:
        print(f"[ollama] no server running (state dir {info['state_dir']})")
    else:
        models = ", ".join(info.get("available_models", [])) or "none"
        answering = "answering" if info["answering"] else "NOT answering"
        print(
            f"[ollama] pid {info['pid']} at {info['host']}, {answering}, version "
            f"{info['version']}, models: {models}, log: {info['log']}"
        )
    return 0 if info["running"] else 3
