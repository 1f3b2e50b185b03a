"""The budget is never exceeded: property tests over random visit orders, batches and resumes.

The reference for the cap is written here with exact rational arithmetic
(``fractions.Fraction``) and checked against the float product too, so the numbers do not
come from the code under test.
"""

from __future__ import annotations

import json
import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.distill import BudgetExceeded, BudgetLedger, DistilledSource, budget_cap
from amuled_ma.errors import AmuledError

torch.set_num_threads(1)

SHARES = st.sampled_from([0.01, 0.03, 0.1, 0.29, 0.3, 1 / 3, 0.5, 0.7, 1.0])
COUNTS = st.integers(min_value=1, max_value=40)


def reference_cap(budget, visited: int) -> int:
    """What the budget allows, from its definition (docs/distill.md)."""
    if isinstance(budget, int):
        return budget
    return max(1, math.floor(Fraction(str(budget)) * visited))  # the decimal as written


def check_invariant(ledger: BudgetLedger) -> None:
    asked, visited, budget = ledger.asked_count, ledger.visited_count, ledger.budget
    assert asked <= reference_cap(budget, visited)
    if isinstance(budget, float):
        # the share holds except for the very first state asked
        assert asked <= Fraction(str(budget)) * visited or asked == 1
    else:
        assert asked <= budget


def test_cap_by_hand():
    assert [budget_cap(0.1, v) for v in (0, 1, 9, 10, 19, 20, 29, 30)] == [1, 1, 1, 1, 1, 2, 2, 3]
    # the decimal as written: 0.3 x 10 is 3 and 0.29 x 100 is 29 (their binary values are
    # slightly below 3/10 and 29/100)
    assert budget_cap(0.3, 10) == 3 and budget_cap(0.29, 100) == 29
    assert budget_cap(1 / 3, 3) == 1 and budget_cap(1 / 3, 30) == 9  # 0.3333333333333333
    assert budget_cap(1.0, 17) == 17 and budget_cap(5, 0) == 5 and budget_cap(5, 1000) == 5


@pytest.mark.parametrize("bad", [0, -1, 0.0, 1.5, float("nan"), True, "0.1", None])
def test_bad_budgets_are_refused(bad):
    with pytest.raises(AmuledError, match="budget"):
        BudgetLedger(bad)


@settings(max_examples=300, deadline=None)
@given(
    budget=st.one_of(SHARES, COUNTS),
    visits=st.lists(st.integers(0, 60), min_size=1, max_size=300),
    batch=st.integers(1, 40),
    greed=st.floats(0, 1),
    resume_at=st.integers(0, 20),
)
def test_the_budget_holds_over_any_visit_order_batching_and_resume(
    budget, visits, batch, greed, resume_at
):
    ledger = BudgetLedger(budget)
    batches = [visits[i : i + batch] for i in range(0, len(visits), batch)]
    for n, keys in enumerate(batches):
        if n == resume_at:  # the state file round trip of a resumed run
            ledger = BudgetLedger.from_dict(json.loads(json.dumps(ledger.to_dict())))
        keys = [f"s{k}" for k in keys]
        ledger.visit(keys)
        candidates = list(dict.fromkeys(k for k in keys if not ledger.is_asked(k)))
        allowed = ledger.allowed()
        take = candidates[: max(0, min(len(candidates), round(greed * (allowed + 3))))]
        if len(take) > allowed:  # more than the budget allows: refused, nothing recorded
            before = (ledger.asked_count, ledger.visited_count)
            with pytest.raises(BudgetExceeded):
                ledger.ask(take)
            assert (ledger.asked_count, ledger.visited_count) == before
            take = take[:allowed]
        ledger.ask(take)
        check_invariant(ledger)
    assert ledger.visited_count == len(set(visits))


def test_asking_twice_or_an_unvisited_state_is_refused():
    ledger = BudgetLedger(1.0)
    ledger.visit(["a", "b"])
    ledger.ask(["a"])
    with pytest.raises(BudgetExceeded, match="already asked"):
        ledger.ask(["a"])
    with pytest.raises(BudgetExceeded, match="not visited"):
        ledger.ask(["c"])


def test_a_state_file_that_breaks_the_budget_is_refused():
    with pytest.raises(AmuledError, match="allows 1"):
        BudgetLedger.from_dict({"budget": 0.1, "visited": ["a", "b"], "asked": ["a", "b"]})
    with pytest.raises(AmuledError, match="not visited"):
        BudgetLedger.from_dict({"budget": 2, "visited": ["a"], "asked": ["b"]})


# --------------------------------------------------------------------- the whole source
ACTIONS = ("up", "down", "left", "right")
MEMBERS = ("care", "virtue", "deontological")


class CountingSource(BeliefSource):
    """Answers every request (a belief that depends on the state), recording each one."""

    name = "counting"
    needs_messages = False

    def __init__(self) -> None:
        self.asked: list[tuple[str, tuple[float, ...]]] = []

    def beliefs(self, requests):
        out = []
        for r in requests:
            self.asked.append((r.cluster, r.obs))
            x = np.asarray(r.obs)
            logits = np.array([x[0], -x[0], x[1], 0.0]) / 4
            p = np.exp(logits - logits.max())
            out.append(BeliefResult(p / p.sum(), "ok", self.name))
        return out


def obs_of(state: int) -> tuple[float, float]:
    return (float(state % 8), float(state // 8))


def requests_of(states: list[int]) -> list[BeliefRequest]:
    return [BeliefRequest("findmilk", m, obs_of(s), ACTIONS) for s in states for m in MEMBERS]


def small(inner, folder, budget, *, resume=False, selection="random"):
    return DistilledSource(
        inner, budget=budget, selection=selection, ensemble=2, hidden=4, refit_every=4,
        seed=7, state_dir=folder, resume=resume, fit_steps=25,
    )  # fmt: skip


@settings(
    max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    budget=st.one_of(st.sampled_from([0.05, 0.1, 0.3]), st.integers(1, 6)),
    visits=st.lists(st.integers(0, 40), min_size=1, max_size=120),
    batch=st.integers(1, 16),
    resume_at=st.integers(0, 10),
    selection=st.sampled_from(["uncertainty", "random"]),
)
def test_the_source_sends_no_request_beyond_the_budget(
    tmp_path_factory, budget, visits, batch, resume_at, selection
):
    """Behind the belief store, as in a run: the LLM is asked only about asked states, once."""
    folder = tmp_path_factory.mktemp("distill")
    llm = CountingSource()
    store = BeliefStore(folder / "beliefs.sqlite")
    source = small(CachedSource(llm, store), folder, budget, selection=selection)
    seen: set[int] = set()
    for n, start in enumerate(range(0, len(visits), batch)):
        if n == resume_at:  # a resumed run: a new process, the state files read back
            spent = (source.ledger.asked_count, source.ledger.visited_count)
            source.close()
            source = small(CachedSource(llm, store), folder, budget, resume=True,
                           selection=selection)  # fmt: skip
            assert (source.ledger.asked_count, source.ledger.visited_count) == spent
        states = list(dict.fromkeys(visits[start : start + batch]))
        results = source.beliefs(requests_of(states))
        seen.update(states)
        assert len(results) == len(states) * len(MEMBERS)
        assert {r.status for r in results} <= {"ok", "distilled"}
        asked = source.ledger.asked_count
        assert source.ledger.visited_count == len(seen)
        assert asked <= reference_cap(budget, len(seen))
        # each asked state costs one request per member, once; no other state is asked
        assert len(llm.asked) == len(set(llm.asked)) == asked * len(MEMBERS)
        assert source.report()["requests_sent"] == len(llm.asked)
    source.close()
    assert len(store) == len(llm.asked)  # the store holds exactly the asked states
    store.close()
