"""The ``amuled`` command line.

Each command group lives in its own module under :mod:`amuled_ma.commands` and
exposes ``register(subparsers)``; this module only discovers and dispatches them,
so adding a command never touches this file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

from amuled_ma import __version__, commands
from amuled_ma.errors import AmuledError


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every discovered command."""
    parser = argparse.ArgumentParser(
        prog="amuled",
        description=(
            "Ethical fine-tuning of RL agents with fused feedback from LLM moral clusters "
            "(AMULED). Run 'amuled COMMAND --help' for a command's options."
        ),
    )
    parser.add_argument("--version", action="version", version=f"amuled-ma {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``amuled`` command line and return its exit code.

    Args:
        argv: Arguments without the program name; ``None`` reads ``sys.argv``.

    Returns:
        0 on success, 1 on a reported error, 130 when interrupted.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    try:
        return int(args.handler(args) or 0)
    except AmuledError as error:
        print(f"amuled: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("amuled: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
