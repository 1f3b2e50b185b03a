"""amuled bench compare: another benchmark on two versions of the code, interleaved."""

from __future__ import annotations

from pathlib import Path

import pytest

from amuled_ma.bench.compare import first_number, parse_table
from amuled_ma.cli import main

ROWS = [
    ("figure", "ours", "reference (authors' code)", "target"),
    ("-" * 34, "-" * 24, "-" * 24, "------"),
    ("FindMilk base run (499,712 steps)", "27.1 s (18,429 steps/s)", "~160 s", "< 30 s"),
    ("Driving greedy collisions / episode", "0.62 ± 0.24", "0.7", "<= 0.7"),
]
# the table as amuled bench train prints it: columns padded, two spaces apart
TABLE = (
    "FindMilk base training ...\n\n"
    + "\n".join("  ".join(f"{c:<34}" for c in row).rstrip() for row in ROWS)
    + "\n\n(torch threads: 1; quick: False)\n"
)


def test_parse_table_reads_the_ours_column():
    rows = parse_table(TABLE)
    assert rows == {
        "FindMilk base run (499,712 steps)": "27.1 s (18,429 steps/s)",
        "Driving greedy collisions / episode": "0.62 ± 0.24",
    }
    assert first_number(rows["FindMilk base run (499,712 steps)"]) == 27.1
    assert first_number("32,768 steps, 1.5 s") == 32768.0
    assert first_number("not reached") is None


@pytest.mark.slow
def test_same_code_twice_gives_the_same_quality_figures(capsys):
    repo = Path(__file__).resolve().parents[1]
    args = ["bench", "compare", "--old", str(repo), "--rounds", "1"]
    args += ["train", "--quick", "--skip", "driving", "finetune", "fusion"]
    assert main(args) == 0
    out = capsys.readouterr().out
    block = out[out.index("FindMilk final greedy optimal") :].splitlines()
    old, new = block[1].split(":", 1)[1].strip(), block[2].split(":", 1)[1].strip()
    assert old == new and old.endswith("%")  # same seed, same code: the same policy
    assert "old/new:" in block[3]


def test_unknown_revision_is_named(capsys):
    assert main(["bench", "compare", "--old", "no-such-rev-xyz", "fusion"]) == 1
    assert "--old no-such-rev-xyz" in capsys.readouterr().err
