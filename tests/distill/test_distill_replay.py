"""End to end on the authors' FindMilk recording: a short distilled fine-tune on a budget.

The panel replays gpt-4o-mini's recorded beliefs; with ``budget = 0.1`` the recording may
be asked about at most 10% of the distinct states the fine-tune visits (at least one), the
rest are answered by the distilled model. The run is interrupted half-way and resumed: the
budget already spent is kept, and ``results.json`` and ``report.md`` carry the accounting.
"""

from __future__ import annotations

import json
import math
from fractions import Fraction

import torch
from tiny_cli import TINY

from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.cli import main

torch.set_num_threads(1)


def test_a_distilled_fine_tune_asks_at_most_its_budget_and_reports_it(
    tmp_path, capsys, monkeypatch, recordings_dir
):
    run_dir = tmp_path / "run"
    common = [
        "--run-dir", str(run_dir), *TINY,
        "--set", f'feedback.recording="{recordings_dir}/findmilk-gpt-4o-mini.json"',
    ]  # fmt: skip
    assert main(["train", "findmilk", "--variant", "base", *common]) == 0
    finetune = [
        "finetune", "findmilk", *common,
        "--set", "finetune.iterations=10", "--set", "finetune.save_interval=1",
        "--set", "feedback.distill.enabled=true", "--set", "feedback.distill.budget=0.1",
        "--set", "feedback.distill.refit_every=4",
    ]  # fmt: skip

    from amuled_ma.learn import population as population_mod

    original = population_mod.PopulationTrainer.iterate
    calls = {"n": 0}

    def stop_at_iteration_5(self):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(population_mod.PopulationTrainer, "iterate", stop_at_iteration_5)
    assert main(finetune) == 130
    folder = run_dir / "finetune-amuled"
    spent = json.loads((folder / "distill.json").read_text())["ledger"]
    assert spent["asked"]  # the budget spent before the interruption is on disk
    monkeypatch.setattr(population_mod.PopulationTrainer, "iterate", original)

    # an edited state file stops the resume with one line, before any state is asked
    honest = (folder / "distill.json").read_text()
    capsys.readouterr()
    for edit, words in (
        (lambda d: d["ledger"]["visited"].append("../../made-up"), "ledger.visited holds"),
        (lambda d: d["asked_obs"][d["ledger"]["asked"][0]].__setitem__(0, math.nan), "finite"),
        (lambda d: d["rng"]["state"].update(state=2**200), "rng.state.state"),
    ):
        document = json.loads(honest)
        edit(document)
        (folder / "distill.json").write_text(json.dumps(document))
        assert main([*finetune, "--resume"]) == 1
        err = capsys.readouterr().err
        assert err.startswith("amuled: error: ") and err.count("\n") == 1, err
        assert words in err and "distill.json" in err and "--force" in err
    (folder / "distill.json").write_text(honest)

    assert main([*finetune, "--resume"]) == 0
    out = capsys.readouterr().out
    assert "feedback budget 10% (uncertainty): asked" in out

    summary = json.loads((folder / "feedback.json").read_text())["distill"]
    ledger = json.loads((folder / "distill.json").read_text())["ledger"]
    visited, asked = len(ledger["visited"]), len(ledger["asked"])
    assert ledger["asked"][: len(spent["asked"])] == spent["asked"]  # kept across the resume
    assert (summary["visited_states"], summary["asked_states"]) == (visited, asked)
    assert visited >= 20 and asked >= 1
    assert asked <= max(1, math.floor(Fraction(1, 10) * visited))  # the budget, by hand
    assert summary["model_states"] == visited - asked and summary["model_answers"] > 0
    # at most one request per panel member and asked state reached the recording, and the
    # store holds no more than those answers (the model's answers are never stored)
    assert summary["requests_sent"] <= 5 * asked
    with BeliefStore(run_dir / "beliefs.sqlite") as store:
        assert len(store) <= 5 * asked
    assert summary["refits"] >= 1 and summary["holdout_states"] >= 0

    assert main(["evaluate", str(run_dir), "--episodes", "2", "--modes", "greedy",
                 "--no-progress"]) == 0  # fmt: skip
    results = json.loads((run_dir / "results.json").read_text())
    entry = results["variants"]["finetune-amuled"]
    assert entry["feedback"]["distill"]["asked_states"] == asked
    assert entry["panel"]["distill"]["budget"] == 0.1
    assert entry["feedback"]["statuses"]["distilled"] > 0
    report = (run_dir / "report.md").read_text()
    assert "## Feedback budget" in report and "| finetune-amuled | 10% | uncertainty |" in report
