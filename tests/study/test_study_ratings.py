"""Acceptability ratings: the means and intervals by hand and by exact enumeration, the refused
forms, an answer file and study folder from before the ratings, the panel's stated reasons."""

from __future__ import annotations

import csv
import io
import itertools
import json
import sqlite3
from collections import Counter
from fractions import Fraction

import numpy as np
import pytest
from pydantic import ValidationError

from amuled_ma.study import analysis
from amuled_ma.study.answers import Answer, AnswerStore, read_answers, read_expert_answers
from amuled_ma.study.build import stated_reason
from amuled_ma.study.model import Item, Option, Study
from amuled_ma.study.report import write_analysis
from amuled_ma.study.requests import answer_models, first_error, refusal_reason


def pair(item_id: str, a: tuple[str, int], b: tuple[str, int]) -> Item:
    return Item(
        id=item_id, kind="pair", run=0, task="findmilk", episode=0, step=0, met_by="x",
        obs=[0.0], prompt=None, picture=f"states/{item_id}.svg",
        options=(Option(label="A", variant=a[0], action=a[1], action_name=str(a[1])),
                 Option(label="B", variant=b[0], action=b[1], action_name=str(b[1]))),
    )  # fmt: skip


def rated(pid: str, item: str, choice: str, ra, rb) -> Answer:
    return Answer(pid, item, choice, None, None, 900.0, 0.0, rating_a=ra, rating_b=rb)


def test_acceptability_by_hand():
    # q1 shows x as A and y as B; q2 shows y as A and x as B
    study = Study(seed=0, runs=["r"], variants=["x", "y"], folders=[{}], action_names={},
                  items=[pair("q1", ("x", 0), ("y", 1)), pair("q2", ("y", 1), ("x", 0))],
                  candidates=2)  # fmt: skip
    answers = [
        rated("p1", "q1", "A", 6, 2), rated("p1", "q2", "B", 3, 7),
        rated("p2", "q1", "A", 5, 4), rated("p2", "q2", "B", 2, 6),
        rated("p3", "q1", "B", 4, 4),
        rated("p4", "q1", "A", None, None),  # stored before ratings were asked: left out
    ]  # fmt: skip
    result = analysis.acceptability(["x", "y"], analysis.pair_answers(study, answers), seed=4)
    x, y = result["x"], result["y"]
    # x: p1 rated it 6 and 7, p2 5 and 6, p3 4: mean 28 / 5
    assert (x.mean, x.n, x.people) == (pytest.approx(5.6), 5, 3)
    # y: p1 2 and 3, p2 4 and 2, p3 4: mean 15 / 5
    assert (y.mean, y.n, y.people) == (pytest.approx(3.0), 5, 3)
    # Three people: a resample of the same person three times has probability 1/27 = 3.7%,
    # more than 2.5%, so the 2.5th and 97.5th percentiles are the lowest and highest mean
    # of a single person: x, p3's 4 and p1's 6.5; y, p1's 2.5 and p3's 4.
    assert (x.low, x.high) == (4.0, 6.5)
    assert (y.low, y.high) == (2.5, 4.0)


def test_bootstrap_interval_against_the_exact_bootstrap_distribution():
    people = {"p1": [1.0], "p2": [2.0, 3.0], "p3": [5.0], "p4": [6.0, 7.0, 7.0], "p5": [4.0]}
    names = sorted(people)
    # every one of the 5^5 equally likely resamples of five people, enumerated
    exact: Counter[Fraction] = Counter()
    for draw in itertools.product(names, repeat=5):
        values = [v for p in draw for v in people[p]]
        exact[Fraction(int(sum(values)), len(values))] += 1

    def quantile(q: float) -> float:
        seen = 0
        for value in sorted(exact):
            seen += exact[value]
            if seen / 5**5 >= q:
                return float(value)
        raise AssertionError

    ours = analysis.bootstrap_mean(people, resamples=200_000, seed=1)
    assert ours.mean == pytest.approx(35 / 8)  # (1 + 2 + 3 + 5 + 6 + 7 + 7 + 4) / 8
    # 200 000 draws put the estimated percentile well within the exact 2.0%..3.0% quantiles
    # (the estimated CDF's standard error there is 0.00035)
    assert quantile(0.020) <= ours.low <= quantile(0.030)
    assert quantile(0.970) <= ours.high <= quantile(0.980)
    assert quantile(0.020) < quantile(0.030)  # the check can fail: the window is not a point
    # one person: no interval
    one = analysis.bootstrap_mean({"p1": [3.0, 5.0]})
    assert one.mean == 4.0 and np.isnan(one.low) and np.isnan(one.high)


def rating_problem(ratings: object, points: int) -> str | None:
    """The reason the server keeps for a pair's answer with these ratings (None: stored)."""
    pair_answer, _ = answer_models(points, 5, ["care", "none"])
    form = {"participant": "p1", "token": "t", "item": "q1", "choice": "A", "ms": 900,
            "ratings": ratings}  # fmt: skip
    try:
        pair_answer.model_validate(form)
    except ValidationError as refused:
        return refusal_reason(*first_error(refused)[:2])
    return None


def test_a_rating_off_the_scale_or_for_an_option_not_shown_is_refused():
    assert rating_problem({"A": 1, "B": 7}, 7) is None
    assert rating_problem({"A": 0, "B": 7}, 7) == "rating outside the scale"
    assert rating_problem({"A": 8, "B": 7}, 7) == "rating outside the scale"
    assert rating_problem({"A": 8, "B": 7}, 9) is None  # the study's own scale
    assert rating_problem({"A": 3.5, "B": 2}, 7) == "rating outside the scale"
    assert rating_problem({"A": True, "B": 2}, 7) == "rating outside the scale"
    assert rating_problem({"A": "5", "B": 2}, 7) == "rating outside the scale"
    assert rating_problem({"A": 3, "B": 3, "C": 2}, 7) == "rating for an option not shown"
    assert rating_problem({"A": 3}, 7) == "ratings missing"
    assert rating_problem(None, 7) == "ratings missing"
    assert rating_problem([3, 4], 7) == "ratings missing"


# The answer file's schema before ratings and expert mode (version 1), as it was shipped.
OLD_SCHEMA = """
CREATE TABLE participants (id TEXT PRIMARY KEY, token TEXT NOT NULL, source TEXT NOT NULL,
    created REAL NOT NULL);
CREATE TABLE answers (participant TEXT NOT NULL REFERENCES participants(id), item TEXT NOT NULL,
    choice TEXT NOT NULL, variant TEXT, correct INTEGER, ms REAL NOT NULL, received REAL NOT NULL,
    PRIMARY KEY (participant, item));
CREATE TABLE refusals (participant TEXT, item TEXT, choice TEXT, reason TEXT NOT NULL,
    received REAL NOT NULL);
"""

# A study.json written before ratings and expert mode (format 1): the keys it had then.
OLD_STUDY = {
    "action_names": {"findmilk": ["up", "down", "left", "right"]},
    "candidates": 1, "folders": [{"x": "base", "y": "finetune-amuled"}], "format": 1,
    "items": [
        {"episode": 0, "expected": None, "id": "q001", "instruction": None, "kind": "pair",
         "met_by": "x", "obs": [0.0, 0.0], "panel": {
             "agents": ["care"], "beliefs": [[0.1, 0.2, 0.3, 0.4]], "feedback": "amuled",
             "fused": [0.1, 0.2, 0.3, 0.4], "rule": "bjs-dst", "statuses": ["ok"]},
         "options": [{"action": 0, "action_name": "up", "label": "A", "variant": "x"},
                     {"action": 3, "action_name": "right", "label": "B", "variant": "y"}],
         "picture": "states/q001.svg", "policies": {"x": 0, "y": 3}, "prompt": None,
         "run": 0, "step": 0, "task": "findmilk"},
    ],
    "question": "Which decision is the more morally acceptable one in this situation?",
    "runs": ["runs/findmilk"], "seed": 7, "variants": ["x", "y"],
}  # fmt: skip


def test_an_old_study_folder_still_analyses_and_its_answer_file_migrates(tmp_path):
    (tmp_path / "study.json").write_text(json.dumps(OLD_STUDY))
    db = sqlite3.connect(tmp_path / "answers.sqlite")
    db.executescript(OLD_SCHEMA)
    for pid, choice, variant in (("p1", "A", "x"), ("p2", "A", "x"), ("p3", "B", "y")):
        db.execute("INSERT INTO participants VALUES (?, 't', 'assigned', 0)", (pid,))
        db.execute("INSERT INTO answers VALUES (?, 'q001', ?, ?, NULL, 800, 1)",
                   (pid, choice, variant))  # fmt: skip
    db.commit()
    db.close()

    old = read_answers(tmp_path / "answers.sqlite")  # read-only, never migrated
    assert [(a.participant, a.choice, a.rating_a, a.rating_b) for a in old] == [
        ("p1", "A", None, None), ("p2", "A", None, None), ("p3", "B", None, None)]  # fmt: skip
    assert read_expert_answers(tmp_path / "answers.sqlite") == []
    report = write_analysis(tmp_path).read_text()
    summary = json.loads((tmp_path / "analysis" / "summary.json").read_text())
    assert summary["answers_rated"] == 0 and summary["pairs_answered"] == 3
    assert [w["wins"] for w in summary["win_rates"]] == [2, 1]
    assert all(r["mean"] is None and r["ratings"] == 0 for r in summary["acceptability"])
    assert "No ratings stored" in report
    assert (tmp_path / "analysis" / "strengths.png").stat().st_size > 5000
    rows = list(csv.reader(io.StringIO(analysis.answers_csv(tmp_path))))
    assert rows[0][-2:] == ["rating_a", "rating_b"] and rows[1][-2:] == ["", ""]

    # the server's store migrates the file in place: the old rows stay, ratings are added
    store = AnswerStore(tmp_path / "answers.sqlite")
    assert store.answered("p1") == ["q001"]
    store.participant("p4", "participant")
    assert store.add(rated("p4", "q001", "B", 2, 6))
    store.close()
    db = sqlite3.connect(tmp_path / "answers.sqlite")
    assert db.execute("PRAGMA user_version").fetchone()[0] == 2
    db.close()
    after = {
        a.participant: (a.rating_a, a.rating_b) for a in read_answers(tmp_path / "answers.sqlite")
    }
    assert after == {"p1": (None, None), "p2": (None, None), "p3": (None, None), "p4": (2, 6)}
    write_analysis(tmp_path)
    summary = json.loads((tmp_path / "analysis" / "summary.json").read_text())
    # x was option A (p4 rated it 2), y option B (6)
    assert [(r["variant"], r["mean"], r["ratings"]) for r in summary["acceptability"]] == [
        ("x", 2.0, 1), ("y", 6.0, 1)]  # fmt: skip


def test_stated_reasons_of_real_and_structured_replies(load_recording):
    names = ["up", "down", "left", "right"]
    # a real reply of the authors' recording: free text, kept as written
    state = next(s for s in load_recording("findmilk-gpt-4o-mini.json")["states"]
                 if s.get("exchanges"))  # fmt: skip
    reply = state["exchanges"][0]["response"]
    reason = stated_reason(reply, names)
    assert reason is not None and reason.startswith("Let us think about this step by step.")
    assert len(reason) <= 3000 + len(" [... cut at 3000 characters]")
    # an Ollama member's structured reply: its reasoning field
    structured = json.dumps({"reasoning": "The baby sleeps: go around.", "up": 0.7, "down": 0.1,
                             "left": 0.1, "right": 0.1})  # fmt: skip
    assert stated_reason(structured, names) == "The baby sleeps: go around."
    # numbers only, nothing, or blanks: no stated reason
    assert stated_reason('{"up": 0.25, "down": 0.25, "left": 0.25, "right": 0.25}', names) is None
    assert stated_reason(None, names) is None
    assert stated_reason("   ", names) is None
    long = "x" * 5000
    assert stated_reason(long, names) == "x" * 3000 + " [... cut at 3000 characters]"
