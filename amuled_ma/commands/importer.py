"""``amuled import authors PATH``: convert the AMULED authors' published artefacts."""

from __future__ import annotations

import argparse
from pathlib import Path

from amuled_ma.commands import _experiment as common


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled import`` and its ``authors`` sub-command."""
    parser = subparsers.add_parser(
        "import",
        help="convert published artefacts (the AMULED authors' caches and policies)",
        description="Convert artefacts published elsewhere into amuled's formats.",
    )
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)
    sub = parser.add_subparsers(dest="import_command", metavar="SOURCE")
    authors = sub.add_parser(
        "authors",
        help="the AMULED authors' LLM caches and CleanRL policies (temetski/moral_agent)",
        description=(
            "Read a checkout of https://github.com/temetski/moral_agent: convert every LLM "
            "cache (models/*_42/*_llm_cache.pickle, PickleCacheAndBaseModels/*/...) into a "
            "recording <task>-<model>.json, found by name by the scenarios' recording key, "
            "and every base and last fine-tuned CleanRL policy into a run folder "
            "<runs>/authors/<task>/ that 'amuled evaluate' accepts. Pickles are read with an "
            "allow-list unpickler (numpy arrays and scalars only) and policies as weights "
            "only. Existing outputs from the same source are kept; other content is never "
            "overwritten without --force."
        ),
    )
    authors.add_argument("path", metavar="PATH", type=Path, help="checkout of the authors' repo")
    authors.add_argument(
        "--to",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder of the recordings (default: $AMULED_DATA/recordings, else "
        "~/.local/share/amuled-ma/recordings)",
    )
    authors.add_argument(
        "--runs",
        type=Path,
        default=Path("runs"),
        metavar="DIR",
        help="folder of runs; policies go to DIR/authors/<task>/ (default: runs)",
    )
    authors.add_argument(
        "--only",
        choices=("recordings", "policies"),
        default=None,
        help="convert only the LLM caches or only the policies (default: both)",
    )
    authors.add_argument(
        "--force", action="store_true", help="replace outputs that exist with other content"
    )
    authors.set_defaults(handler=import_authors_command)


def import_authors_command(args: argparse.Namespace) -> int:
    """Run ``amuled import authors``."""
    from amuled_ma.authors.checkout import import_authors

    report = import_authors(
        args.path,
        to=args.to,
        runs=args.runs,
        force=args.force,
        recordings=args.only in (None, "recordings"),
        policies=args.only in (None, "policies"),
    )
    marks = {"new": "+", "replaced": "!", "unchanged": "="}
    recordings = report.of_kind("recording")
    if recordings:
        common.say(f"recordings in {report.recordings_dir}:")
        for o in recordings:
            common.say(f"  {marks[o.status]} {o.target.name}: {o.detail} (from {o.source})")
    policies = report.of_kind("policy")
    if policies:
        common.say(f"policies in {report.runs_dir}:")
        for o in policies:
            shown = o.target.relative_to(report.runs_dir)
            common.say(f"  {marks[o.status]} {shown}: {o.detail} (from {o.source})")
    for note in report.notes:
        common.say(f"  note: {note}")
    common.say("(+ written, = already there from the same source, ! replaced with --force)")
    if recordings:
        example = recordings[0].target.stem
        common.say(f"a scenario names a recording by name, e.g. recording = {example!r}")
    for task in sorted({o.target.parent.name for o in policies}):
        common.say(f"evaluate with: amuled evaluate {report.runs_dir / task}")
    return 0
