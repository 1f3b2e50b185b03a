"""The paper's row beside ours, and the one sentence on whether AMULED moved from the base.

The paper's figures asserted here are copied from ``docs/reproduction.md`` (section "As the
authors ran it", column *paper (their notebook)*), not from the module under test; every
interval is worked out by hand below from the hand-made statistics.
"""

from __future__ import annotations

import math

import pytest

from amuled_ma.evaluate.paper import PAPER_ROWS, paper_row
from amuled_ma.evaluate.report.tables import difference_ci, movement_sentence, paper_table
from amuled_ma.evaluate.report.writing import write_report
from amuled_ma.evaluate.results import Results, Stat
from amuled_ma.evaluate.stats import mean_ci


def stat(mean: float, std: float, n: int = 10) -> dict:
    return {"mean": mean, "std": std, "n": n, "half_width": 0.0}


def results(amuled: dict[str, dict], base: dict[str, dict]) -> Results:
    def entry(metrics: dict[str, dict]) -> dict:
        return {"metrics": metrics, "ci_over": "episodes", "n_seeds": 1}

    return Results.model_validate(
        {
            "scenario": "findmilk-demo",
            "task": "findmilk",
            "episodes": 10,
            "confidence": 0.95,
            "seed": 42,
            "variants": {
                "base": {"sampled": entry(base), "greedy": entry(base)},
                "finetune-amuled": {
                    "sampled": entry(amuled),
                    "greedy": entry(amuled),
                    "panel": {"feedback": "amuled", "recipe": "authors", "source": "replay"},
                },
            },
        }
    )


BASE = {
    "steps_to_milk": stat(14.0, 0.0),
    "crying_pacified": stat(3.6, 1.0),
    "sleeping_woken": stat(3.1, 1.0),
    "reached_milk": stat(1.0, 0.0),
}


@pytest.mark.parametrize(
    ("task", "variant", "values"),
    [  # docs/reproduction.md, "paper (their notebook)"
        ("findmilk", "finetune-amuled", (14.2, 4.9, 0.6)),
        ("findmilk", "finetune-human", (14.9, 3.0, 1.5)),
        ("findmilk", "base", (14.0, 4.0, 3.8)),
        ("findmilk", "shaped", (14.0, 5.0, 0.0)),
        ("findmilk", "finetune-cluster-care", (14.0, 5.0, 0.6)),
        ("findmilk", "finetune-agg-mean", (14.0, 4.0, 1.5)),
        ("driving", "finetune-amuled", (2.0, 13.6, 54.2)),
        ("driving", "base", (1.0, 5.9, 16.2)),
        ("driving", "shaped", (12.5, 19.1, 167.1)),
        ("driving", "finetune-moral", (7.4, 9.2, 53.8)),
    ],
)
def test_paper_rows_are_the_papers_figures(task, variant, values):
    row = paper_row(task, variant)
    assert row is not None
    assert tuple(row.values.values()) == values
    assert paper_row(task, f"{variant}.seed43") == row  # a seed replica maps to its row


def test_every_task_has_the_13_rows_of_the_papers_tables():
    assert {task: len(rows) for task, rows in PAPER_ROWS.items()} == {"findmilk": 13, "driving": 13}
    assert paper_row("findmilk", "finetune-amuled-live") is None


def test_difference_interval_is_welchs():
    # n = 10 each, std 1 each: variance of the difference 0.1 + 0.1 = 0.2; Welch df
    # 0.2^2 / (2 * 0.1^2 / 9) = 18; t(0.975, 18) = 2.1009 (printed tables);
    # half = 2.1009 * sqrt(0.2)
    diff, low, high = difference_ci(Stat(**stat(1.0, 1.0)), Stat(**stat(3.1, 1.0)))
    half = 2.1009 * math.sqrt(0.2)
    assert diff == pytest.approx(-2.1)
    assert (low, high) == pytest.approx((-2.1 - half, -2.1 + half), abs=1e-4)
    # deterministic greedy policies: the difference itself
    assert difference_ci(Stat(**stat(1.0, 0.0)), Stat(**stat(4.0, 0.0))) == (-3.0, -3.0, -3.0)
    # one value on a side: no spread, no interval
    assert difference_ci(Stat(**stat(1.0, 1.0)), Stat(**stat(4.0, 0.0, n=1))) is None


def test_difference_interval_is_rs_welch_test_on_the_sleep_data():
    # R's example(t.test): t.test(extra ~ group, data = sleep) prints "df = 17.776" and
    # "95 percent confidence interval: -3.3654832  0.2054832" (Welch, fractional df)
    group1 = [0.7, -1.6, -0.2, -1.2, -0.1, 3.4, 3.7, 0.8, 0.0, 2.0]
    group2 = [1.9, 0.8, 1.1, 0.1, -0.1, 4.4, 5.5, 1.6, 4.6, 3.4]
    diff, low, high = difference_ci(Stat(**mean_ci(group1)), Stat(**mean_ci(group2)))
    assert diff == pytest.approx(0.75 - 2.33)
    assert (low, high) == pytest.approx((-3.3654832, 0.2054832), abs=1e-7)


def test_sentence_says_amuled_wakes_fewer_sleeping_babies_with_the_interval():
    amuled = {**BASE, "sleeping_woken": stat(1.0, 1.0)}
    text = movement_sentence(results(amuled, BASE), mode="sampled")
    half = 2.1009 * math.sqrt(0.2)  # as above
    assert text.startswith("AMULED (finetune-amuled, sampled policy) wakes 2.10 fewer sleeping")
    assert f"(95% CI {2.1 - half:.2f} to {2.1 + half:.2f} fewer)" in text
    assert "no difference beyond noise in steps to the milk, crying babies" in text


def test_sentence_says_when_amuled_did_not_move():
    amuled = {**BASE, "sleeping_woken": stat(3.0, 1.0)}  # 0.1 fewer: inside +-0.94
    text = movement_sentence(results(amuled, BASE), mode="sampled")
    assert "did not move from the base beyond noise" in text


def test_sentence_says_a_fine_tune_that_misses_the_milk():
    amuled = {**BASE, "reached_milk": stat(0.6, 0.5), "steps_to_milk": stat(128.0, 140.0)}
    text = movement_sentence(results(amuled, BASE), mode="sampled")
    assert "takes 114.00 more steps to the milk" in text
    assert "reaches the milk in only 60% of the episodes" in text


def test_report_puts_the_papers_row_beside_ours_with_the_recipe(tmp_path):
    amuled = {**BASE, "sleeping_woken": stat(1.0, 1.0)}
    data = results(amuled, BASE)
    table = paper_table(data, {"finetune-amuled": "authors"})
    rows = {line.split(" | ")[0].strip("| "): line for line in table.splitlines()}
    assert (
        "| 14.2 / 4.9 / 0.6 | 14.00 ± 0.00 / 3.60 ± 0.00 / 1.00 ± 0.00 | authors |"
        in (rows["finetune-amuled"])
    )
    assert "| 14.0 / 4.0 / 3.8 |" in rows["base"] and rows["base"].endswith("| - |")
    text = write_report(tmp_path, data, title="t").read_text()
    assert "## What AMULED did, beside the paper" in text
    assert "- AMULED (finetune-amuled, sampled policy) wakes 2.10 fewer sleeping babies" in text
    assert "| 14.2 / 4.9 / 0.6 |" in text
    assert "the authors' notebook" in text
