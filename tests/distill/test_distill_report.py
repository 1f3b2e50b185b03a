"""The report of a budget ablation: the accounting table, metrics against the budget, figure."""

from __future__ import annotations

from amuled_ma.evaluate.evaluator import merge_feedback
from amuled_ma.evaluate.report.bars import budget_points
from amuled_ma.evaluate.report.tables import agents_table, budget_ablation_table, budget_table
from amuled_ma.evaluate.report.writing import write_report
from amuled_ma.evaluate.results import Results
from amuled_ma.evaluate.stats import mean_ci
from amuled_ma.records.run_record import RunRecord

#: A two-step FindMilk episode on the paper's layout (for the trajectory figure).
TRAJECTORY = {
    "obs": [[0, 0, 7, 7, 0, 0, 0, 0], [1, 0, 7, 7, 0, 0, 0, 0]],
    "actions": [3],
    "events": {},
    "layout": {"crying": [[2, 2], [2, 3], [4, 4], [5, 6], [6, 7]],
               "sleeping": [[1, 1], [3, 3], [4, 0], [5, 4], [5, 5], [6, 6]]},
}  # fmt: skip


def stats(values: dict[str, list[float]]) -> dict:
    metrics = {m: mean_ci(v) for m, v in values.items()}
    return {"metrics": metrics, "n_seeds": 1, "trajectory": TRAJECTORY}


def distilled(asked: int, visited: int, tv: float | None) -> dict:
    return {
        "budget": None, "selection": None, "visited_states": visited, "asked_states": asked,
        "asked_share": asked / visited, "cap": asked, "model_states": visited - asked,
        "requests_forwarded": 5 * asked, "requests_sent": 5 * asked, "model_answers": 900,
        "miss_answers": 0, "unasked_answers": 0, "refits": 4, "holdout_states": 2,
        "holdout_tv": {"care": 0.2, "virtue": 0.3}, "holdout_tv_fused": tv,
    }  # fmt: skip


def variant(budget, selection, sleeping, asked, tv):
    report = {**distilled(asked, 100, tv), "budget": budget, "selection": selection}
    agents = {"care": {"ok": 10, "distilled": 90, "total": 100, "failed": 0}}
    return {
        "greedy": stats({"steps_to_milk": [14, 14, 15], "sleeping_woken": sleeping}),
        "panel": {"feedback": "amuled", "distill": {"enabled": True, "budget": budget,
                                                   "selection": selection}},
        "feedback": {"feedback": "amuled", "distill": report, "agents": agents},
    }  # fmt: skip


def results() -> Results:
    return Results.model_validate(
        {
            "scenario": "findmilk",
            "task": "findmilk",
            "confidence": 0.95,
            "variants": {
                "base": {"greedy": stats({"steps_to_milk": [14] * 3, "sleeping_woken": [4, 4, 3]})},
                "finetune-amuled": {
                    "greedy": stats({"steps_to_milk": [14] * 3, "sleeping_woken": [1, 2, 1]}),
                    "panel": {"feedback": "amuled"},
                },
                "finetune-amuled-budget1": variant(1.0, "uncertainty", [1, 1, 2], 100, 0.1),
                "finetune-amuled-budget0.1-uncertainty": variant(
                    0.1, "uncertainty", [2, 2, 3], 10, 0.3
                ),
                "finetune-amuled-budget0.1-random": variant(0.1, "random", [3, 3, 3], 10, None),
            },
        }
    )


def test_budget_points_and_the_full_feedback_run():
    points, full = budget_points(results())
    assert full == "finetune-amuled"
    assert [(p["selection"], p["budget"]) for p in points] == [
        ("all", 1.0), ("random", 0.1), ("uncertainty", 0.1),
    ]  # fmt: skip


def test_the_tables_carry_the_accounting_and_the_metrics():
    table = budget_table(results())
    row = "| finetune-amuled-budget0.1-uncertainty | 10% | uncertainty | 100 | 10 (10.0%) | 90 |"
    assert row in table and "50 / 50" in table and "0.300 (2 states)" in table
    assert "care 0.200, virtue 0.300" in table
    assert "finetune-amuled |" not in table.replace("finetune-amuled-", "")  # not distilled
    ablation = budget_ablation_table(results())
    lines = ablation.splitlines()
    assert lines[0].startswith("| selection | budget | variant | asked | requests sent |")
    row = "| uncertainty | 10% | finetune-amuled-budget0.1-uncertainty | 10 of 100 |"
    assert any(line.startswith(row) for line in lines)
    assert lines[-1].startswith("| full feedback | 100% | finetune-amuled | every state |")
    agents = agents_table(results())
    assert "by the model" in agents.splitlines()[0] and "90.0%" in agents


def test_the_report_has_the_tables_and_the_figure(tmp_path):
    # the run's record (its config.json) names the ablation; the caller hands it over
    run = RunRecord.model_validate({"ablation": "budget"})
    report = write_report(tmp_path, results(), title="budget", run=run).read_text()
    assert "## Feedback budget" in report and "## Metrics against the budget" in report
    assert "![Ablation of the feedback budget](ablation_budget.png)" in report
    assert (tmp_path / "ablation_budget.png").stat().st_size > 10_000


def test_seed_replicas_sum_the_counts_and_average_the_distances():
    one = {"statuses": {"ok": 10, "distilled": 90}, "distill": distilled(10, 100, 0.2)}
    two = {"statuses": {"ok": 12, "distilled": 88}, "distill": distilled(12, 110, 0.4)}
    merged = merge_feedback([one, two])
    assert merged["failure_rate"] == 0.0  # the model's answers are answers
    d = merged["distill"]
    assert (d["visited_states"], d["asked_states"], d["requests_sent"]) == (210, 22, 110)
    assert d["asked_share"] == 22 / 210 and abs(d["holdout_tv_fused"] - 0.3) < 1e-12
    assert d["replicas"] == 2
