"""``DistilledSource``: states, statuses, misses, held-out agreement, the state files, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.distill import DistilledSource
from amuled_ma.distill.state import EXAMPLES_FILE, LEDGER_FILE
from amuled_ma.errors import AmuledError

torch.set_num_threads(1)

ACTIONS = ("up", "down", "left", "right")
MEMBERS = ("care", "virtue")


def belief_of(obs, member: str) -> np.ndarray:
    x = float(obs[0])
    peak = 0 if x < 4 else 1
    if member == "virtue":
        peak = 3
    out = np.full(4, 0.1)
    out[peak] = 0.7
    return out


class Panel(BeliefSource):
    """Answers each member by :func:`belief_of`; ``miss`` members get a replay miss."""

    name = "panel"
    needs_messages = False

    def __init__(self, miss: tuple[str, ...] = (), on_call=None) -> None:
        self.miss = miss
        self.calls: list[list[BeliefRequest]] = []
        self.on_call = on_call

    def beliefs(self, requests):
        if self.on_call is not None:
            self.on_call(requests)
        self.calls.append(list(requests))
        return [
            BeliefResult(np.full(4, 0.25), "replay_miss", self.name)
            if r.cluster in self.miss and r.obs[0] % 2 == 1
            else BeliefResult(belief_of(r.obs, r.cluster), "ok", self.name)
            for r in requests
        ]


def requests(states, members=MEMBERS, prompt: str | None = None):
    out = []
    for s in states:
        for m in members:
            messages = (("user", f"{prompt} {m}"),) if prompt is not None else ()
            out.append(BeliefRequest("findmilk", m, (float(s), 0.0), ACTIONS, messages))
    return out


def source(inner, tmp_path=None, **kwargs) -> DistilledSource:
    options = {"ensemble": 2, "hidden": 8, "seed": 5, "fit_steps": 60, **kwargs}
    return DistilledSource(inner, state_dir=tmp_path, **options)


def test_statuses_ask_within_budget_and_answer_the_rest_by_the_model():
    inner = Panel()
    distilled = source(inner, budget=0.25, selection="random")
    results = distilled.beliefs(requests(range(8)))
    statuses = [r.status for r in results]
    assert statuses.count("ok") == 2 * 2 and statuses.count("distilled") == 6 * 2
    report = distilled.report()
    assert (report["visited_states"], report["asked_states"], report["model_states"]) == (8, 2, 6)
    assert report["requests_forwarded"] == report["requests_sent"] == 4
    assert report["model_answers"] == 12 and report["refits"] >= 1
    for r in results:
        assert r.belief.shape == (4,) and abs(r.belief.sum() - 1) < 1e-12
    # the same states again: nothing new is asked, the asked ones' answers are kept (one
    # forward per process, also without a store)
    again = distilled.beliefs(requests(range(8)))
    assert distilled.ledger.asked_count == 2 and distilled.ledger.visited_count == 8
    assert len(inner.calls) == 1 and distilled.report()["requests_forwarded"] == 4
    assert [r.status for r in again] == statuses


def test_a_state_is_its_observation_and_its_chat():
    inner = Panel()
    distilled = source(inner, budget=1.0)
    distilled.beliefs(requests([1], prompt="4 crying babies"))
    distilled.beliefs(requests([1], prompt="3 crying babies"))  # same obs, another prompt
    distilled.beliefs(requests([1], prompt="4 crying babies"))
    assert distilled.ledger.visited_count == 2 and distilled.ledger.asked_count == 2


def test_a_member_without_any_answer_is_unasked_and_misses_can_be_answered():
    inner = Panel(miss=("virtue",))
    plain = source(inner, budget=1)  # one state asked: obs 1, where virtue misses
    results = plain.beliefs(requests([1, 2, 4]))
    asked = requests([1, 2, 4])
    by = {(r.cluster, r.obs[0]): res.status for r, res in zip(asked, results, strict=True)}
    assert by[("care", 1.0)] == "ok" and by[("virtue", 1.0)] == "replay_miss"
    assert by[("care", 2.0)] == "distilled" and by[("virtue", 2.0)] == "unasked"
    assert plain.report()["unasked_answers"] == 2

    inner = Panel(miss=("virtue",))
    answering = source(inner, budget=1.0, answer_misses=True)
    answering.beliefs(requests([2]))  # virtue answers at 2: the model learns it
    results = answering.beliefs(requests([3]))  # asked; virtue misses at 3
    virtue = results[1]
    assert virtue.status == "distilled_miss" and virtue.extra["inner_status"] == "replay_miss"
    assert answering.report()["miss_answers"] == 1
    assert abs(virtue.belief.sum() - 1) < 1e-12


def test_held_out_states_measure_the_agreement_with_the_panel():
    inner = Panel()
    distilled = source(inner, budget=1.0, holdout=0.5, fusion_rule="mean")
    distilled.beliefs(requests(range(8)))
    report = distilled.report()
    assert report["holdout_states"] == 4  # every second asked state
    assert set(report["holdout_tv"]) == set(MEMBERS)
    # the fused agreement by hand: the mean rule is the members' average
    held = [
        distilled._examples[k]
        for n, k in enumerate(distilled.ledger.asked)
        if n % 2 == 1  # the 2nd, 4th, ... asked state
    ]
    obs = np.array([e.obs for e in held])
    pred = distilled.model.predict(obs).mean(1)
    real = np.array([[e.beliefs[m] for m in MEMBERS] for e in held]).mean(1)
    expected = 0.5 * np.abs(pred - real).sum(-1).mean()
    assert report["holdout_tv_fused"] == pytest.approx(expected, abs=1e-9)


def test_the_same_seed_and_visits_give_the_same_answers():
    def run(seed):
        distilled = source(Panel(), budget=0.2, seed=seed)
        out = []
        for start in range(0, 20, 5):
            out += [r.belief for r in distilled.beliefs(requests(range(start, start + 5)))]
        return np.array(out)

    assert np.array_equal(run(1), run(1))
    assert not np.array_equal(run(1), run(2))


def test_the_budget_is_written_before_the_panel_is_asked(tmp_path):
    seen = []

    def check(batch):
        ledger = json.loads((tmp_path / LEDGER_FILE).read_text())
        seen.append(len(ledger["ledger"]["asked"]))

    distilled = source(Panel(on_call=check), tmp_path, budget=0.5)
    distilled.beliefs(requests(range(4)))
    assert seen == [2]  # already on disk when the 2 asked states were sent
    assert not list(tmp_path.glob("*.tmp"))


def test_resume_keeps_the_budget_already_spent(tmp_path):
    store = BeliefStore(tmp_path / "beliefs.sqlite")
    inner = Panel()
    first = source(CachedSource(inner, store), tmp_path, budget=3)
    first.beliefs(requests(range(5)))
    assert first.ledger.asked_count == 3
    sent = len([r for call in inner.calls for r in call])
    first.close()
    assert (tmp_path / EXAMPLES_FILE).is_file()

    again = source(CachedSource(inner, store), tmp_path, budget=3, resume=True)
    assert again.ledger.asked_count == 3 and again.ledger.visited_count == 5
    assert again.model is not None and again.generation >= 1  # refitted from the pairs
    results = again.beliefs(requests(range(5, 12)))  # new states: the budget is spent
    assert {r.status for r in results} == {"distilled"}
    again.beliefs(requests(range(5)))  # asked ones come from the store: nothing sent
    assert len([r for call in inner.calls for r in call]) == sent
    report = again.report()
    assert report["asked_states"] == 3 and report["requests_sent"] == sent
    assert report["requests_forwarded"] > sent
    again.close()
    assert len(store) == 3 * len(MEMBERS)  # the store holds exactly the asked states
    store.close()

    fresh = source(Panel(), tmp_path, budget=3)  # not a resume: starts over
    assert fresh.ledger.asked_count == 0 and not (tmp_path / EXAMPLES_FILE).exists()


def test_resume_with_other_settings_or_a_damaged_file_is_refused(tmp_path):
    first = source(Panel(), tmp_path, budget=0.5)
    first.beliefs(requests(range(4)))
    first.close()
    with pytest.raises(AmuledError, match=r"budget: 0\.5 -> 0\.3.*--force") as err:
        source(Panel(), tmp_path, budget=0.3, resume=True)
    assert LEDGER_FILE in str(err.value)
    (tmp_path / LEDGER_FILE).write_text("{not json")
    with pytest.raises(AmuledError, match=f"{LEDGER_FILE}.*--force"):
        source(Panel(), tmp_path, budget=0.5, resume=True)


def test_a_cut_last_line_of_the_pairs_is_skipped(tmp_path):
    first = source(Panel(), tmp_path, budget=1.0)
    first.beliefs(requests(range(3)))
    first.close()
    with (tmp_path / EXAMPLES_FILE).open("a") as handle:
        handle.write('{"key": "abc", "obs": [1.0,')  # a crash while it was written
    again = source(Panel(), tmp_path, budget=1.0, resume=True)
    assert len(again._examples) == 3
