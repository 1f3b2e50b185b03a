"""``amuled beliefs stats|export|import``: inspect and move the persistent belief store."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from amuled_ma.beliefs.store.database import BeliefStore, default_store_path
from amuled_ma.beliefs.store.interchange import export_jsonl, import_jsonl
from amuled_ma.beliefs.store.rows import BeliefStoreError
from amuled_ma.beliefs.types import STATUSES
from amuled_ma.files.safe import atomic_writer


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled beliefs`` and its sub-commands."""
    parser = subparsers.add_parser(
        "beliefs",
        help="inspect, export and import the persistent belief store",
        description=(
            "The belief store keeps every LLM answer (SQLite). Export it as JSON Lines on one "
            "machine and import it on another to replay a run without the model."
        ),
    )
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)
    sub = parser.add_subparsers(dest="beliefs_command", metavar="COMMAND")

    def store_option(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--store",
            type=Path,
            default=None,
            help=f"belief store file (default: ${{AMULED_BELIEF_STORE}} or {default_store_path()})",
        )

    stats = sub.add_parser("stats", help="rows per status, model, task and cluster; integrity")
    store_option(stats)
    stats.add_argument("--json", action="store_true", help="print the figures as JSON")
    stats.set_defaults(handler=_stats)

    export = sub.add_parser("export", help="write the store's rows as JSON Lines")
    store_option(export)
    export.add_argument(
        "-o", "--output", default="-", help="output file ('-' for standard output, the default)"
    )
    export.add_argument(
        "--status",
        action="append",
        choices=STATUSES,
        help="only rows with this status (repeatable; default: all)",
    )
    export.add_argument("--task", default=None, help="only rows of this task")
    export.set_defaults(handler=_export)

    imp = sub.add_parser("import", help="read JSON Lines written by 'export' into the store")
    store_option(imp)
    imp.add_argument("files", nargs="+", help="JSONL files ('-' for standard input)")
    imp.add_argument(
        "--no-verify",
        action="store_true",
        help="keep rows whose key does not match their content (default: refuse them)",
    )
    imp.set_defaults(handler=_import)


def _existing_store(path: Path | None) -> BeliefStore:
    """Open an existing store for reading only (``mode=ro``): works on read-only files."""
    path = path or default_store_path()
    if not path.is_file():
        raise BeliefStoreError(
            f"no belief store at {path} (give --store PATH or set AMULED_BELIEF_STORE)"
        )
    return BeliefStore(path, read_only=True)


def _stats(args: argparse.Namespace) -> int:
    with _existing_store(args.store) as store:
        figures = store.stats()
        figures["integrity"] = store.integrity_check()
    if args.json:
        print(json.dumps(figures, indent=2))
        return 0
    print(f"belief store {figures['path']} (schema v{figures['schema_version']})")
    if figures["open_mode"] == "immutable":
        print(
            "  opened immutable (the file and its folder are not writable): rows still in a "
            "-wal file beside it are not counted"
        )
    print(f"  rows: {figures['rows']} ({figures['cacheable_rows']} served as answers)")
    print("  by status: " + ", ".join(f"{k} {v}" for k, v in sorted(figures["by_status"].items())))
    for entry in figures["by_model"]:
        model = f", model {entry['model']}" if entry["model"] is not None else ""
        print(f"  source {entry['source']}{model}: {entry['rows']} rows")
    for entry in figures["by_task_cluster"]:
        print(f"  {entry['task']} / {entry['cluster']}: {entry['rows']} rows")
    lat = figures["latency_s"]
    if lat["count"]:
        print(f"  latency: mean {lat['mean']:.3f} s, total {lat['total']:.1f} s")
    tok = figures["tokens"]
    print(f"  tokens: prompt {tok['prompt']}, completion {tok['completion']}")
    print(f"  distinct message texts: {figures['distinct_texts']}")
    sizes = ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in figures["file_bytes"].items())
    print(f"  files: {sizes}")
    print(f"  integrity: {'; '.join(figures['integrity'])}")
    return 0 if figures["integrity"] == ["ok"] else 1


def _export(args: argparse.Namespace) -> int:
    with _existing_store(args.store) as store:
        if args.output == "-":
            try:
                count = export_jsonl(store, sys.stdout, status=args.status, task=args.task)
                sys.stdout.flush()
            except BrokenPipeError:  # `amuled beliefs export | head`: the reader left
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
                return 0
        elif Path(args.output).exists() and not Path(args.output).is_file():
            # a device or a pipe (/dev/stdout, a FIFO): written in place, never replaced
            with open(args.output, "w", encoding="utf-8") as fp:
                count = export_jsonl(store, fp, status=args.status, task=args.task)
        else:
            # written beside the target and renamed at the end: a row that cannot be
            # exported (a damaged store) leaves no half-written file behind; a link in the
            # target's place is refused, never followed
            with atomic_writer(args.output, text=True) as fp:
                count = export_jsonl(store, fp, status=args.status, task=args.task)
    print(f"exported {count} rows from {store.path}", file=sys.stderr)
    return 0


def _import(args: argparse.Namespace) -> int:
    path = args.store or default_store_path()
    with BeliefStore(path) as store:
        for name in args.files:
            if name == "-":
                counts = import_jsonl(store, sys.stdin, name="<stdin>", verify=not args.no_verify)
            else:
                try:
                    fp = open(name, encoding="utf-8")  # noqa: SIM115 - closed below
                except OSError as error:
                    raise BeliefStoreError(f"{name}: cannot read: {error}") from error
                with fp:
                    counts = import_jsonl(store, fp, name=name, verify=not args.no_verify)
            print(
                f"{name}: read {counts['read']} rows, wrote {counts['written']} "
                f"(answers already in {path} are kept)"
            )
    return 0
