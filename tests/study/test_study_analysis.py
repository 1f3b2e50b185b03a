"""The study's numbers against hand computations and a second implementation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from amuled_ma.study import analysis
from amuled_ma.study.answers import Answer
from amuled_ma.study.model import Item, Option, PanelView, Study


def item(item_id: str, a: tuple[str, int], b: tuple[str, int], fused=None, policies=None) -> Item:
    panel = None
    if fused is not None:
        panel = PanelView(feedback="amuled", agents=["care"], rule="bjs-dst",
                          beliefs=[list(fused)], statuses=["ok"], fused=list(fused))  # fmt: skip
    return Item(
        id=item_id, kind="pair", run=0, task="findmilk", episode=0, step=0, met_by="base",
        obs=[0.0], prompt=None, picture=f"states/{item_id}.svg",
        options=(Option(label="A", variant=a[0], action=a[1], action_name=str(a[1])),
                 Option(label="B", variant=b[0], action=b[1], action_name=str(b[1]))),
        policies=policies or {a[0]: a[1], b[0]: b[1]}, panel=panel,
    )  # fmt: skip


def answer(participant: str, item_id: str, choice: str, correct=None) -> Answer:
    return Answer(participant, item_id, choice, None, correct, 1000.0, 0.0)


def test_win_rates_by_hand_and_wilson_against_its_formula_s_textbook_value():
    games = [("a", "b"), ("a", "b"), ("b", "a"), ("a", "c"), ("c", "b")]
    rates = {w.variant: (w.wins, w.n, w.rate) for w in analysis.win_rates("abc", games)}
    assert rates == {"a": (3, 4, 0.75), "b": (1, 4, 0.25), "c": (1, 2, 0.5)}
    # Wilson's interval for 3/4 (Newcombe 1998, method 3): 0.3006 to 0.9544
    low, high = analysis.wilson(3, 4)
    assert (round(low, 4), round(high, 4)) == (0.3006, 0.9544)


def test_krippendorff_s_own_worked_example():
    # Krippendorff (2011), "Computing Krippendorff's alpha-reliability", nominal data of
    # 4 observers and 12 units with missing values: alpha = 0.743
    nan = np.nan
    data = [
        [1, 2, 3, 3, 2, 1, 4, 1, 2, nan, nan, nan],
        [1, 2, 3, 3, 2, 2, 4, 1, 2, 5, nan, 3],
        [nan, 3, 3, 3, 2, 3, 4, 2, 2, 5, 1, nan],
        [1, 2, 3, 3, 2, 4, 4, 1, 2, 5, 1, nan],
    ]
    import krippendorff

    alpha = krippendorff.alpha(reliability_data=data, level_of_measurement="nominal")
    assert round(alpha, 3) == 0.743


def test_reliability_of_choices_by_hand():
    # two raters, four pairs: A A B B and A B B B. Coincidences: o_AA = 2, o_BB = 4,
    # o_AB = o_BA = 1; n_A = 3, n_B = 5, n = 8: alpha = 1 - (n - 1) * 2 / (2 * 3 * 5) = 8/15
    items = [item(f"q{i}", ("x", 0), ("y", 1)) for i in range(4)]
    pairs = [(answer("r1", it.id, c), it) for it, c in zip(items, "AABB", strict=True)]
    pairs += [(answer("r2", it.id, c), it) for it, c in zip(items, "ABBB", strict=True)]
    assert analysis.nominal_alpha(analysis.choice_values(pairs)) == pytest.approx(8 / 15, abs=1e-12)


def mm_bradley_terry(n: int, games, iterations: int = 5000) -> np.ndarray:
    """Hunter's (2004) MM algorithm: p_i <- W_i / sum_j n_ij / (p_i + p_j)."""
    wins = np.zeros(n)
    count = np.zeros((n, n))
    for w, lo in games:
        wins[w] += 1
        count[w, lo] += 1
        count[lo, w] += 1
    p = np.ones(n)
    for _ in range(iterations):
        p = wins / (count / (p[:, None] + p[None, :])).sum(axis=1)
        p /= p.sum()
    logs = np.log(p)
    return logs - logs.mean()


def test_bradley_terry_equals_the_mm_algorithm():
    names = ["amuled", "base", "human", "shaped"]
    rng = np.random.default_rng(3)
    truth = np.array([1.0, -0.5, 0.3, -0.8])
    games = []
    for _ in range(400):
        i, j = rng.choice(4, size=2, replace=False)
        p = 1 / (1 + math.exp(truth[j] - truth[i]))
        games.append((i, j) if rng.random() < p else (j, i))
    named = [(names[w], names[lo]) for w, lo in games]
    ours = analysis.bradley_terry(names, named, alpha=0.0)
    np.testing.assert_allclose(ours, mm_bradley_terry(4, games), atol=1e-4)
    assert np.argmax(ours) == 0 and np.argmin(ours) == 3


def test_agreement_and_majority_by_hand():
    items = [
        # panel prefers action 0 (option A); policy x takes 0, y takes 1, z takes 2 (neither)
        item("q1", ("x", 0), ("y", 1), fused=[0.6, 0.3, 0.1], policies={"x": 0, "y": 1, "z": 2}),
        # panel prefers action 1 (option B)
        item("q2", ("y", 2), ("x", 1), fused=[0.1, 0.6, 0.3], policies={"x": 1, "y": 2, "z": 1}),
        # tie among people: no majority
        item("q3", ("x", 0), ("y", 1), fused=[0.5, 0.5, 0.0]),
    ]
    names = {"findmilk": ["0", "1", "2"]}
    study = Study(
        seed=0,
        runs=["r"],
        variants=["x", "y"],
        folders=[{}],
        action_names=names,
        items=items,
        candidates=3,
    )
    answers = [answer("p1", "q1", "A"), answer("p2", "q1", "A"), answer("p3", "q1", "B"),
               answer("p1", "q2", "A"), answer("p2", "q2", "A"), answer("p3", "q2", "A"),
               answer("p1", "q3", "A"), answer("p2", "q3", "B")]  # fmt: skip
    pairs = analysis.pair_answers(study, answers)
    majority = analysis.majorities(pairs)
    assert majority == {"q1": ("A", 2, 3), "q2": ("A", 3, 3)}
    accepted = {"q1": {0}, "q2": {2}}  # the majority's option's action
    agree = analysis.agreement(study, accepted, pairs=True)
    # q1: majority A (action 0): fused agrees; q2: majority A (action 2): fused prefers 1
    assert agree["fused"] == [1, 2] and agree["cluster:care"] == [1, 2]
    # x: q1 takes 0 (agree), q2 takes 1 (the other option); y: q1 disagrees, q2 agrees;
    # z: q1 takes 2 (neither option, not counted), q2 takes 1 (disagrees)
    assert agree["policy:x"] == [1, 2] and agree["policy:y"] == [1, 2]
    assert agree["policy:z"] == [0, 1]
    games = analysis.comparisons(pairs)
    assert games[:3] == [("x", "y"), ("x", "y"), ("y", "x")]


def test_attention_failures_are_left_out():
    answers = [answer("p1", "q9", "A", correct=1), answer("p2", "q9", "B", correct=0),
               answer("p3", "q1", "A")]  # fmt: skip
    assert analysis.attentive(answers) == {"p1", "p3"}
    assert analysis.attentive(answers, keep_inattentive=True) == {"p1", "p2", "p3"}
