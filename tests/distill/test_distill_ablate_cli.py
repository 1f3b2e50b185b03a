"""``amuled ablate findmilk --what budget`` end to end on a tiny run (rule-based panel)."""

from __future__ import annotations

import json
import math
from fractions import Fraction

from tiny_cli import RULES, TINY

from amuled_ma.cli import main


def test_ablate_budget_trains_evaluates_and_reports(tmp_path, capsys):
    run_dir = tmp_path / "run"
    args = ["ablate", "findmilk", "--what", "budget", "--run-dir", str(run_dir)]
    assert main([*args, "--episodes", "2", "--jobs", "1", *TINY, *RULES]) == 0
    out = capsys.readouterr().out
    assert "ablate findmilk --what budget: 8 variants x 1 seed(s) done" in out
    assert "feedback budget 3% (random): asked" in out
    folder = run_dir / "ablate-budget"
    results = json.loads((folder / "results.json").read_text())
    variants = results["variants"]
    distilled = {n: v for n, v in variants.items() if "distill" in (v.get("panel") or {})}
    assert len(distilled) == 7 and "finetune-amuled" in results["variants"]
    for entry in distilled.values():
        report = entry["feedback"]["distill"]
        share = Fraction(str(report["budget"]))  # the decimal as written
        assert report["asked_states"] <= max(1, math.floor(share * report["visited_states"]))
    report = (folder / "report.md").read_text()
    assert "## Metrics against the budget" in report and "## Feedback budget" in report
    assert "| full feedback | 100% | finetune-amuled |" in report
    assert (folder / "ablation_budget.png").is_file()
