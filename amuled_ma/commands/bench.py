"""``amuled bench NAME``: benchmarks that print figures, discovered from `amuled_ma.bench`."""

from __future__ import annotations

import argparse

from amuled_ma import bench
from amuled_ma.commands import public_modules


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled bench`` and one sub-command per benchmark module."""
    parser = subparsers.add_parser(
        "bench",
        help="run a benchmark and print its figures",
        description="Benchmarks print throughput figures measured side by side in one run.",
    )
    names = parser.add_subparsers(dest="bench", metavar="NAME")
    for name, module in public_modules(bench):
        doc = (module.__doc__ or "").strip()
        sub = names.add_parser(
            name,
            help=doc.splitlines()[0] if doc else None,
            description=doc or None,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(sub)
        sub.set_defaults(handler=module.main)
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)
