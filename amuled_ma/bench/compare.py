"""Another benchmark, run on two versions of the code side by side, interleaved.

``amuled bench compare --old REV train`` runs the benchmark with ``REV`` (a temporary
worktree) and this checkout alternately for ``--rounds`` rounds, and prints each figure per
round with the ratio old mean / new mean (above 1: the new code is faster for a time).
Interleaving puts both under the same machine load.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from amuled_ma.errors import AmuledError

#: A benchmark table row: figure, then the "ours" column, two spaces or more apart.
_ROW = re.compile(r"^(?P<figure>\S.*?)\s{2,}(?P<ours>\S.*?)(\s{2,}.*)?$")
_NUMBER = re.compile(r"-?\d[\d,]*(?:\.\d+)?")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the comparison's options."""
    parser.add_argument(
        "--old",
        required=True,
        metavar="REV_OR_DIR",
        help="the old code: a git revision of this repository (e.g. HEAD~1) or a source folder",
    )
    parser.add_argument(
        "--rounds", type=int, default=2, help="old/new pairs to run, interleaved (default 2)"
    )
    parser.add_argument(
        "benchmark",
        nargs=argparse.REMAINDER,
        help="the benchmark and its options, e.g. train --skip fusion",
    )


def parse_table(output: str) -> dict[str, str]:
    """``{figure: ours}`` from a benchmark's printed table (rows after the dashed rule)."""
    rows: dict[str, str] = {}
    lines = output.splitlines()
    for i, line in enumerate(lines):
        if set(line.replace(" ", "")) == {"-"} and i > 0:
            for row in lines[i + 1 :]:
                if not row.strip():
                    break
                match = _ROW.match(row)
                if match:
                    rows[match["figure"].strip()] = match["ours"].strip()
    return rows


def first_number(text: str) -> float | None:
    """The first number in a figure (``"27.1 s (18,429 steps/s)"`` -> 27.1)."""
    match = _NUMBER.search(text)
    return float(match.group().replace(",", "")) if match else None


def _source_root(old: str, keep: list[Path]) -> Path:
    """A folder holding the old ``amuled_ma`` package: the folder given, or a worktree."""
    folder = Path(old)
    if (folder / "amuled_ma").is_dir():
        return folder
    repo = Path(__file__).resolve().parents[2]
    tmp = Path(tempfile.mkdtemp(prefix="amuled-old-"))
    done = subprocess.run(
        ["git", "-C", str(repo), "worktree", "add", "--detach", "-f", str(tmp / "src"), old],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise AmuledError(
            f"--old {old}: neither a folder with amuled_ma/ nor a git revision of {repo} "
            f"({done.stderr.strip().splitlines()[-1] if done.stderr.strip() else 'git failed'})"
        )
    keep.append(tmp / "src")
    return tmp / "src"


def _run(root: Path, benchmark: list[str], recordings: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(root)}
    if recordings.is_dir():  # a worktree in a temporary folder has no ../shared beside it
        env.setdefault("AMULED_RECORDINGS", str(recordings))
    done = subprocess.run(
        [sys.executable, "-m", "amuled_ma.bench", *benchmark],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-3:]
        raise AmuledError(f"bench {' '.join(benchmark)} failed with {root}: {' | '.join(tail)}")
    return done.stdout


def main(args: argparse.Namespace) -> int:
    """Run the benchmark with the old and the new code, interleaved; print the figures."""
    benchmark = [a for a in args.benchmark if a != "--"]
    if not benchmark:
        raise AmuledError("name the benchmark to compare, e.g. amuled bench compare --old "
                          "HEAD~1 train --skip fusion")  # fmt: skip
    if args.rounds < 1:
        raise AmuledError(f"--rounds: expected at least 1, got {args.rounds}")
    worktrees: list[Path] = []
    new_root = Path(__file__).resolve().parents[2]
    try:
        old_root = _source_root(args.old, worktrees)
        runs: dict[str, list[dict[str, str]]] = {"old": [], "new": []}
        for r in range(args.rounds):
            for label, root in (("old", old_root), ("new", new_root)):
                print(f"round {r + 1}/{args.rounds}: {label} code ({root}) ...", flush=True)
                output = _run(root, benchmark, new_root.parent / "shared" / "amuled-recordings")
                runs[label].append(parse_table(output))
    finally:
        for tree in worktrees:
            subprocess.run(
                ["git", "-C", str(new_root), "worktree", "remove", "--force", str(tree)],
                capture_output=True,
                check=False,
            )
    figures = list(dict.fromkeys(f for run in runs["new"] + runs["old"] for f in run))
    print(f"\namuled bench {' '.join(benchmark)}: old = {args.old}, new = this checkout")
    for figure in figures:
        old = [run.get(figure, "-") for run in runs["old"]]
        new = [run.get(figure, "-") for run in runs["new"]]
        o = [v for v in map(first_number, old) if v is not None]
        n = [v for v in map(first_number, new) if v is not None]
        ratio = f"{(sum(o) / len(o)) / (sum(n) / len(n)):.2f}" if o and n and sum(n) else "-"
        print(f"\n{figure}\n  old: {' | '.join(old)}\n  new: {' | '.join(new)}\n  old/new: {ratio}")
    return 0
