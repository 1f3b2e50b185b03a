"""A tiny trained FindMilk run (base, the rules panel, the rule-based human) and its study."""

from __future__ import annotations

from pathlib import Path

from tiny_cli import RULES, TINY

from amuled_ma.cli import main


def tiny_run(folder: Path) -> Path:
    run = folder / "findmilk"
    common = ["findmilk", "--run-dir", str(run), *TINY]
    assert main(["train", *common, *RULES]) == 0
    assert main(["finetune", *common, *RULES]) == 0
    assert main(["finetune", *common, "--feedback", "human:rules"]) == 0
    return run
