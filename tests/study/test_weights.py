"""Panel weights learned from people, against raters simulated from known member weights.

The raters follow the fusion with a known prior ``rho``: a rater picks option A with
probability ``f_a / (f_a + f_b)``, ``f = fuse(beliefs, prior=rho)`` (the plain Luce rule).
The fit does not know ``rho``; its 95% intervals must hold it, its held-out likelihood must
beat the paper's fixed weights when ``rho`` is skewed, and must not when ``rho`` is uniform.
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest

from amuled_ma.cli import main
from amuled_ma.errors import AmuledError
from amuled_ma.fusion import fuse
from amuled_ma.scenario.panel_weights import PanelWeights
from amuled_ma.study import weights as sw
from amuled_ma.study.answers import Answer, AnswerStore
from amuled_ma.study.model import ANSWERS_FILE, Item, Option, PanelView, Study, write_study

MEMBERS = ["consequentialist", "deontological", "virtue", "care", "social_justice"]
SKEWED = np.array([0.4, 0.3, 0.15, 0.1, 0.05])
UNIFORM = np.full(5, 0.2)


def panel_items(beliefs: np.ndarray, rng: np.random.Generator, statuses=None) -> list[Item]:
    """One pair item per belief matrix ``(K, A)``, two distinct actions drawn at random."""
    items = []
    for n, b in enumerate(beliefs):
        a, c = (int(x) for x in rng.choice(b.shape[1], size=2, replace=False))
        status = statuses[n] if statuses is not None else ["ok"] * len(MEMBERS)
        panel = PanelView(feedback="amuled", agents=MEMBERS, rule="bjs-dst",
                          beliefs=b.tolist(), statuses=status, fused=fuse(b).tolist())  # fmt: skip
        options = (
            Option(label="A", variant="x", action=a, action_name=str(a)),
            Option(label="B", variant="y", action=c, action_name=str(c)),
        )
        items.append(
            Item(id=f"q{n:03d}", kind="pair", run=0, task="findmilk", episode=0, step=n,
                 met_by="base", obs=[0.0], prompt=None, picture=f"states/q{n:03d}.svg",
                 options=options, panel=panel)
        )  # fmt: skip
    return items


def study_of(items: list[Item]) -> Study:
    return Study(seed=0, runs=["runs/x"], variants=["x", "y"], folders=[{}],
                 action_names={"findmilk": ["up", "down", "left", "right"]}, items=items,
                 candidates=len(items))  # fmt: skip


def luce(item: Item, rho: np.ndarray) -> float:
    """The simulated raters' probability of A: f_a / (f_a + f_b), f fused with prior rho."""
    assert item.panel is not None
    f = fuse(np.array(item.panel.beliefs), prior=rho)
    a, b = (o.action for o in item.options)
    with np.errstate(invalid="ignore"):  # 0 / 0: no member believes in either action
        return float(f[a] / (f[a] + f[b]))


def raters(items: list[Item], rho: np.ndarray, people: int, seed: int) -> list[Answer]:
    rng = np.random.default_rng(seed)
    probs = [luce(item, rho) for item in items]
    return [
        Answer(f"p{p:03d}", item.id, "A" if rng.random() < prob else "B", None, None, 900.0, 0.0)
        for p in range(people)
        for item, prob in zip(items, probs, strict=True)
    ]


def dirichlet_items(seed: int, count: int = 30) -> list[Item]:
    rng = np.random.default_rng(seed)
    return panel_items(rng.dirichlet(np.ones(4), size=(count, len(MEMBERS))), rng)


def test_the_fit_recovers_known_member_weights_within_its_intervals():
    items = dirichlet_items(0)
    answers = raters(items, SKEWED, people=60, seed=1)
    data = sw.choice_data(study_of(items), answers)
    result = sw.fit_study(data, bootstrap=200, folds=5, seed=0)
    low, high, est = result.low, result.high, result.learned.prior
    assert np.all((low <= SKEWED) & (high >= SKEWED)), (low, SKEWED, high)
    assert np.abs(est - SKEWED).max() < 0.05
    assert np.all(high - low < 0.12)  # intervals narrow enough to say something
    # the order of the members is recovered
    assert np.argsort(-est).tolist() == [0, 1, 2, 3, 4]
    # the raters follow the plain Luce rule: the temperature is 1 within its interval
    t_low, t_high = result.temperature_interval
    assert t_low <= 1.0 <= t_high
    # held out, the learned weights predict the raters better than the paper's fixed ones
    held = result.held_out
    assert held.learned > held.fixed and held.difference_low > 0
    assert held.answers == 60 * 30 and held.folds == 5


def test_uniform_raters_give_intervals_around_uniform_and_no_held_out_gain():
    items = dirichlet_items(10)
    answers = raters(items, UNIFORM, people=60, seed=20)
    result = sw.fit_study(sw.choice_data(study_of(items), answers), bootstrap=200, seed=0)
    assert np.all((result.low <= 0.2) & (result.high >= 0.2)), (result.low, result.high)
    assert np.abs(result.learned.prior - 0.2).max() < 0.04
    # four more parameters fitted to noise do not predict held-out raters better
    assert result.held_out.difference_low < 0


def test_the_intervals_are_about_as_wide_as_the_estimates_spread():
    """Coverage over replicated studies (same items, new raters): the intervals hold."""
    items = dirichlet_items(4)
    study = study_of(items)
    estimates, spreads, inside = [], [], []
    for replicate in range(8):
        answers = raters(items, SKEWED, people=60, seed=100 + replicate)
        result = sw.fit_study(sw.choice_data(study, answers), bootstrap=100, folds=2, seed=0)
        estimates.append(result.learned.prior)
        spreads.append(result.draws.std(axis=0))
        inside.append((result.low <= SKEWED) & (result.high >= SKEWED))
    # too narrow intervals are the failure to catch: the bootstrap's spread is not much
    # below the spread of the estimates over the replicates (8 replicates: a noisy
    # figure, hence the loose bound), and the intervals hold the truth
    ratio = np.mean(spreads, axis=0) / np.std(estimates, axis=0)
    assert np.all(ratio > 0.5), ratio
    assert np.mean(inside) >= 0.8  # 40 intervals at a nominal 95%


def test_recorded_beliefs_as_items(load_recording):
    """Items made of the authors' real LLM beliefs (Llama 3.1 70B on Driving).

    Real members agree more than random ones and often give an action 0: most items say
    little about the weights (a handful of 30 did, tried here), so this study has 100.
    """
    recording = load_recording("driving-llama-3_1-70b.json")
    beliefs = np.array(
        [[s["beliefs"][c] for c in recording["clusters"]] for s in recording["states"]]
    )
    beliefs = beliefs[~np.all(beliefs == beliefs[:, :1], axis=(1, 2))]
    rng = np.random.default_rng(0)
    chosen = beliefs[rng.choice(len(beliefs), 100, replace=False)]
    # a pair of actions that no member believes in at all has no Luce probability: left out
    items = [i for i in panel_items(chosen, rng) if math.isfinite(luce(i, SKEWED))]
    answers = raters(items, SKEWED, people=60, seed=1)
    result = sw.fit_study(sw.choice_data(study_of(items), answers), bootstrap=200, seed=0)
    assert np.all((result.low <= SKEWED) & (result.high >= SKEWED)), (result.low, result.high)
    assert result.held_out.difference_low > 0


def test_the_choice_probability_is_the_fusion_with_the_prior():
    """The fit's closed form against ``fuse(..., prior=rho)``, abstentions included."""
    rng = np.random.default_rng(9)
    beliefs = rng.dirichlet(np.ones(4), size=(12, 5))
    beliefs[3, :, 2] = 0.0  # zeros, as real replies have
    beliefs[3] /= beliefs[3].sum(axis=1, keepdims=True)
    statuses = [["ok"] * 5 for _ in range(12)]
    statuses[1][2] = "abstained"
    statuses[5][0] = statuses[5][4] = "replay_miss"
    statuses[7] = ["timeout"] * 4 + ["ok"]  # one member alone: its own belief
    items = panel_items(beliefs, rng, statuses)
    answers = [Answer("p1", i.id, "A", None, None, 1.0, 0.0) for i in items]
    data = sw.choice_data(study_of(items), answers)
    rho = np.array([0.1, 0.5, 0.2, 0.15, 0.05])
    for tau in (1.0, 2.5):
        got = sw.choice_probability(data, rho, tau)
        for n, item in enumerate(items):
            answered = [j for j, s in enumerate(statuses[n]) if s == "ok"]
            f = fuse(beliefs[n][answered], prior=rho[answered])
            a, b = (o.action for o in item.options)
            p = f[a] ** tau / (f[a] ** tau + f[b] ** tau)
            assert got[n] == pytest.approx(sw.FLOOR + (1 - 2 * sw.FLOOR) * p, abs=1e-12)
    assert data.size.tolist()[:8] == [5, 4, 5, 5, 5, 3, 5, 1]


def test_beliefs_rounded_as_the_study_file_keeps_them_are_fitted():
    """Rows of 6-decimal beliefs sum to 1 only within 2e-6, beyond fusion's 1e-6."""
    rng = np.random.default_rng(4)
    exact = rng.dirichlet(np.ones(4), size=(40, 5))
    rounded = np.round(exact, 6)
    assert np.abs(rounded.sum(axis=2) - 1).max() > 1e-6  # fuse() refuses such a row
    exact_items = panel_items(exact, np.random.default_rng(1))
    rounded_items = [
        i.model_copy(update={"panel": i.panel.model_copy(update={"beliefs": r.tolist()})})
        for i, r in zip(exact_items, rounded, strict=True)
    ]
    answers = [Answer("p1", i.id, "A", None, None, 1.0, 0.0) for i in exact_items]
    rho = np.array([0.1, 0.5, 0.2, 0.15, 0.05])
    want = sw.choice_probability(sw.choice_data(study_of(exact_items), answers), rho, 1.0)
    got = sw.choice_probability(sw.choice_data(study_of(rounded_items), answers), rho, 1.0)
    assert got == pytest.approx(want, abs=1e-5)


def test_the_gradient_is_the_likelihood_s_slope():
    items = dirichlet_items(6, count=10)
    data = sw.choice_data(study_of(items), raters(items, SKEWED, people=5, seed=0))
    n_a, n_b = data.counts()
    x = np.array([0.3, -0.2, 0.1, 0.5, -0.4, 0.2])
    mask = np.ones(6, dtype=bool)
    _, grad = sw._objective(x, x, mask, data, n_a, n_b)
    step = 1e-6
    for j in range(6):
        e = np.zeros(6)
        e[j] = step
        up = sw._objective(x + e, x, mask, data, n_a, n_b)[0]
        down = sw._objective(x - e, x, mask, data, n_a, n_b)[0]
        assert grad[j] == pytest.approx((up - down) / (2 * step), rel=1e-5, abs=1e-6)


def test_inattentive_participants_are_left_out():
    items = dirichlet_items(8, count=4)
    check = Item(id="q900", kind="attention", run=0, task="findmilk", episode=0, step=0,
                 met_by="base", obs=[0.0], prompt=None, picture="states/q900.svg",
                 options=(Option(label="A", variant=None, action=0, action_name="0"),
                          Option(label="B", variant=None, action=1, action_name="1")),
                 expected="A", instruction="choose A")  # fmt: skip
    study = study_of([*items, check])
    answers = raters(items, SKEWED, people=3, seed=0)
    answers += [Answer("p000", "q900", "A", None, 1, 1.0, 0.0),
                Answer("p001", "q900", "B", None, 0, 1.0, 0.0)]  # fmt: skip
    assert sw.choice_data(study, answers).participants == ("p000", "p002")
    kept = sw.choice_data(study, answers, keep_inattentive=True)
    assert kept.participants == ("p000", "p001", "p002") and len(kept.answer_item) == 12


def write_folder(folder, items, answers) -> None:
    folder.mkdir()
    write_study(folder, study_of(items))
    store = AnswerStore(folder / ANSWERS_FILE)
    try:
        for person in sorted({a.participant for a in answers}):
            store.participant(person, "participant")
        for answer in answers:
            assert store.add(answer)
    finally:
        store.close()


def test_fit_weights_writes_a_file_a_scenario_can_read(tmp_path, capsys):
    items = dirichlet_items(0)
    folder = tmp_path / "study"
    write_folder(folder, items, raters(items, SKEWED, people=60, seed=1))
    argv = ["study", "fit-weights", str(folder), "--bootstrap", "50", "--seed", "3"]
    assert main([*argv, "--no-progress"]) == 0
    out = capsys.readouterr().out
    path = folder / "analysis" / "weights.json"
    assert f"weights {path}" in out and "held-out log-likelihood per answer" in out
    assert "consequentialist" in out.splitlines()[1]
    weights = PanelWeights.model_validate(json.loads(path.read_text()))
    assert weights.members == MEMBERS and math.isclose(sum(weights.weights), 1.0, abs_tol=1e-5)
    assert weights.participants == 60 and weights.answers == 1800 and weights.items == 30
    assert all(
        lo <= w <= hi for lo, w, hi in zip(weights.low, weights.weights, weights.high, strict=True)
    )
    study_hash = hashlib.sha256((folder / "study.json").read_bytes()).hexdigest()
    assert weights.provenance.study_sha256 == study_hash
    assert weights.provenance.seed == 3 and weights.provenance.bootstrap == 50
    first = path.read_bytes()
    assert main([*argv, "--no-progress", "-o", str(tmp_path / "again.json")]) == 0
    assert (tmp_path / "again.json").read_bytes() == first  # same study and seed: same bytes


def test_a_fixed_temperature_is_kept_and_said(tmp_path, capsys):
    items = dirichlet_items(0)
    folder = tmp_path / "study"
    write_folder(folder, items, raters(items, SKEWED, people=60, seed=1))
    argv = ["study", "fit-weights", str(folder), "--bootstrap", "30", "--temperature", "1"]
    assert main([*argv, "--no-progress"]) == 0
    assert "choice temperature 1.000 (fixed)" in capsys.readouterr().out
    weights = PanelWeights.model_validate_json((folder / "analysis" / "weights.json").read_text())
    assert weights.temperature == 1.0 and weights.provenance.fixed_temperature == 1.0
    assert weights.temperature_interval == (1.0, 1.0)
    assert max(abs(w - t) for w, t in zip(weights.weights, SKEWED, strict=True)) < 0.05


def test_refusals_are_one_line_before_any_fit(tmp_path, capsys):
    items = dirichlet_items(0, count=3)
    plain = [i.model_copy(update={"panel": None}) for i in items]
    folder = tmp_path / "nopanel"
    write_folder(folder, plain, raters(items, SKEWED, people=2, seed=0))
    assert main(["study", "fit-weights", str(folder), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bjs-dst" in err and "amuled study build" in err
    folder = tmp_path / "few"
    write_folder(folder, items, raters(items, SKEWED, people=3, seed=0))
    assert main(["study", "fit-weights", str(folder), "--folds", "5", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--folds 5" in err and "3 participants" in err
    with pytest.raises(AmuledError, match=r"no study\.json"):
        sw.fit_weights(tmp_path / "nothing")
