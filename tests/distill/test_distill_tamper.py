"""A state file edited between two runs is refused with one line; the budget cannot grow.

Before these checks, raising ``ledger.budget`` in ``distill.json`` let a resumed run ask
far more states than the scenario's budget (245 under a budget of 20), and negative,
huge or string counters were copied into the report or ended in a traceback.
"""

from __future__ import annotations

import json

import pytest
import torch
from sparse_files import sparse
from test_distill_source import MEMBERS, Panel, requests, source

from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.distill.state import (
    EXAMPLES_FILE,
    LEDGER_FILE,
    MAX_EXAMPLE_LINE_BYTES,
    MAX_EXAMPLES_BYTES,
    MAX_LEDGER_BYTES,
)
from amuled_ma.errors import AmuledError

torch.set_num_threads(1)

BUDGET = 3


def spend(tmp_path, budget=BUDGET):
    """A first run: 6 states visited, ``budget`` asked; returns the store (open)."""
    store = BeliefStore(tmp_path / "beliefs.sqlite")
    first = source(CachedSource(Panel(), store), tmp_path, budget=budget)
    first.beliefs(requests(range(6)))
    first.close()
    return store


def edit(tmp_path, change) -> None:
    path = tmp_path / LEDGER_FILE
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def resume(tmp_path, store, budget=BUDGET):
    return source(CachedSource(Panel(), store), tmp_path, budget=budget, resume=True)


def assert_one_line_refusal(info) -> None:
    message = str(info.value)
    assert "\n" not in message
    assert LEDGER_FILE in message or EXAMPLES_FILE in message
    assert "--force" in message


@pytest.mark.parametrize(
    ("budget", "forged"), [(BUDGET, 1000), (BUDGET, 1.0), (0.5, 1.0), (0.5, 1)]
)
def test_a_raised_ledger_budget_is_refused_and_nothing_more_is_asked(tmp_path, budget, forged):
    store = spend(tmp_path, budget)
    rows = len(store)
    assert rows == 3 * len(MEMBERS)  # 3 of 6 states: a count of 3, or a share of 0.5

    def raise_budget(data):
        data["ledger"]["budget"] = forged

    edit(tmp_path, raise_budget)
    with pytest.raises(AmuledError, match=r"ledger\.budget is .* but the scenario") as info:
        again = resume(tmp_path, store, budget)
        again.beliefs(requests(range(6, 300)))  # what the old code then asked
        again.close()
    assert_one_line_refusal(info)
    assert len(store) == rows  # the store rows: nothing more was asked
    store.close()


@pytest.mark.parametrize(
    ("counter", "value"),
    [
        ("refits", -5),
        ("requests_sent", 10**30),
        ("model_answers", "many"),
        ("requests_forwarded", 2.5),
        ("miss_answers", True),
        ("requests_sent", 10**6),  # more sent than forwarded
        ("refits", 500),  # more fits than asked states
    ],
)
def test_forged_counters_are_refused_with_one_line(tmp_path, counter, value):
    store = spend(tmp_path)

    def forge(data):
        data["counters"][counter] = value

    edit(tmp_path, forge)
    with pytest.raises(AmuledError, match=f"counters.{counter}") as info:
        resume(tmp_path, store).report()
    assert_one_line_refusal(info)
    store.close()


@pytest.mark.parametrize("value", [-1, "3", 10**9, None])
def test_a_forged_generation_is_refused(tmp_path, value):
    store = spend(tmp_path)
    edit(tmp_path, lambda data: data.update(generation=value))
    with pytest.raises(AmuledError, match="generation is") as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    store.close()


def test_asked_states_removed_from_the_ledger_are_found_by_their_answers(tmp_path):
    # forgetting the asked states would give the budget back; their answers remain
    store = spend(tmp_path)

    def forget(data):
        data["ledger"]["asked"] = []
        data["asked_obs"] = {}
        data["counters"]["refits"] = data["generation"] = 0

    edit(tmp_path, forget)
    with pytest.raises(AmuledError, match="never asked") as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    store.close()


@pytest.mark.parametrize(
    "change",
    [
        lambda d: d["ledger"].update(asked=[1, 2, 3]),
        lambda d: d["ledger"].update(visited="abc"),
        lambda d: d.update(ledger="x"),
        lambda d: d.update(counters="x"),
        lambda d: d["counters"].pop("refits"),
    ],
)
def test_malformed_tables_are_refused_with_one_line(tmp_path, change):
    store = spend(tmp_path)
    edit(tmp_path, change)
    with pytest.raises(AmuledError) as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    store.close()


def test_honest_resumes_never_ask_more_than_the_budget(tmp_path):
    store = spend(tmp_path)
    for start in range(6, 60, 18):  # three more runs, each resuming the last
        again = resume(tmp_path, store)
        again.beliefs(requests(range(start, start + 18)))
        report = again.report()
        again.close()
        assert report["asked_states"] == report["cap"] == BUDGET
    assert len(store) == BUDGET * len(MEMBERS)  # counted in the store itself
    store.close()


def test_a_ledger_over_1_gib_is_refused_unread_with_one_line(tmp_path):
    assert MAX_LEDGER_BYTES == 2**30
    store = spend(tmp_path)
    sparse(tmp_path / LEDGER_FILE, MAX_LEDGER_BYTES + 1)
    with pytest.raises(AmuledError) as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    assert f"the budget state is {MAX_LEDGER_BYTES + 1:,} bytes, more than the " in str(info.value)
    assert f"{MAX_LEDGER_BYTES:,} a budget state may be" in str(info.value)
    store.close()


def test_a_training_pairs_file_over_2_gib_is_refused_unread(tmp_path):
    assert MAX_EXAMPLES_BYTES == 2**31
    store = spend(tmp_path)
    sparse(tmp_path / EXAMPLES_FILE, MAX_EXAMPLES_BYTES + 1)
    with pytest.raises(AmuledError) as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    assert f"the training-pairs file is {MAX_EXAMPLES_BYTES + 1:,} bytes" in str(info.value)
    store.close()


def test_a_training_pairs_line_over_1_mib_is_refused_with_its_line_number(tmp_path):
    # a 1 GiB line of zeros after the real ones (sparse): never read whole
    store = spend(tmp_path)
    path = tmp_path / EXAMPLES_FILE
    lines = path.read_bytes().count(b"\n")
    sparse(path, 2**30)
    with pytest.raises(AmuledError) as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    message = str(info.value)
    assert message.startswith(f"{path}:{lines + 1}: a line longer than the ")
    assert f"{MAX_EXAMPLE_LINE_BYTES:,} bytes a line may be" in message
    store.close()


def test_a_cut_last_line_of_the_training_pairs_is_still_skipped(tmp_path):
    store = spend(tmp_path)
    path = tmp_path / EXAMPLES_FILE
    with open(path, "ab") as handle:
        handle.write(b'{"key": "cut sh')  # a crash while the line was written
    again = resume(tmp_path, store)
    assert again.ledger.asked_count == BUDGET
    again.close()
    store.close()


def made_up_keys(n: int) -> list[str]:
    """``n`` keys that look like a fine-tune's (32 hex digits) but name no state visited."""
    return [f"{k:032x}" for k in range(10**6, 10**6 + n)]


def test_made_up_visited_states_never_raise_the_requests_sent(tmp_path):
    # a share of 0.1: 20 states visited, 2 asked; 100,000 made-up visited states would let
    # floor(0.1 x 100,020) = 10,002 states be asked under a cap taken from the file
    honest, forged = tmp_path / "honest", tmp_path / "forged"
    sent = {}
    for folder in (honest, forged):
        folder.mkdir()
        store = BeliefStore(folder / "beliefs.sqlite")
        first = source(CachedSource(Panel(), store), folder, budget=0.1)
        first.beliefs(requests(range(20)))
        first.close()
        assert len(store) == 2 * len(MEMBERS)
        if folder is forged:
            edit(folder, lambda d: d["ledger"]["visited"].extend(made_up_keys(100_000)))
        inner = Panel()
        again = source(CachedSource(inner, store), folder, budget=0.1, resume=True)
        again.beliefs(requests(range(20, 60)))
        again.close()
        sent[folder.name] = sum(len(call) for call in inner.calls)
        report = again.report()
        # the cap counts the asked and the re-visited states only: 2 + 40 of them
        assert report["cap"] == 4
        assert len(store) == 4 * len(MEMBERS)  # asked states' rows: within 0.1 x 42
        store.close()
    assert sent["forged"] == sent["honest"]


@pytest.mark.parametrize(
    ("field", "value"),
    [("visited", "../../etc"), ("visited", "x" * 32), ("visited", "ABCDEF" * 6)],
)
def test_ledger_entries_that_are_not_state_keys_are_refused(tmp_path, field, value):
    store = spend(tmp_path)
    edit(tmp_path, lambda d: d["ledger"][field].append(value))
    with pytest.raises(AmuledError, match=f"ledger.{field} holds") as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    store.close()


def forge_obs(data, value):
    key = next(iter(data["asked_obs"]))
    data["asked_obs"][key][0] = value


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda d: d["rng"]["state"].update(state=2**200), "rng.state.state"),
        (lambda d: d["rng"].update(bit_generator="MT19937"), "rng.bit_generator"),
        (lambda d: d["rng"].update(has_uint32=7), "rng.has_uint32"),
        (lambda d: d.update(obs_dim=10**9), "obs_dim"),
        (lambda d: d.update(obs_dim=3), "obs_dim is 3"),
        (lambda d: forge_obs(d, float("nan")), "finite number"),
        (lambda d: forge_obs(d, float("inf")), "finite number"),
        (lambda d: forge_obs(d, "1.0"), "valid number"),
        (lambda d: d.update(members=["care", "care"]), "not distinct"),
        (lambda d: d.update(actions=[]), "actions"),
    ],
)
def test_every_numeric_field_of_the_ledger_is_checked(tmp_path, change, words):
    store = spend(tmp_path)
    path = tmp_path / LEDGER_FILE
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))  # json writes NaN and Infinity, as an editor may
    with pytest.raises(AmuledError, match=words) as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    store.close()


def edit_example(tmp_path, change) -> None:
    path = tmp_path / EXAMPLES_FILE
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    change(lines[0])
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda r: r["beliefs"].update(care=[0.001] * 1000), "has 1000 value"),
        (lambda r: r["beliefs"].update(care=[float("nan")] * 4), "finite number"),
        (lambda r: r["beliefs"].update(care=[-0.5, 0.5, 0.5, 0.5]), "negative"),
        (lambda r: r["beliefs"].update(evil=[0.25] * 4), "not a member"),
        (lambda r: r.update(obs=[float("inf"), 0.0]), "finite number"),
        (lambda r: r.update(obs=[1.0] * 7), "obs has 7 values"),
        (lambda r: r.update(key="zz"), "key"),
        (lambda r: r.update(extra=1), "extra"),
    ],
)
def test_every_training_pair_is_checked(tmp_path, change, words):
    store = spend(tmp_path)
    edit_example(tmp_path, change)
    with pytest.raises(AmuledError, match=words) as info:
        resume(tmp_path, store)
    assert_one_line_refusal(info)
    assert f"{EXAMPLES_FILE}:1: " in str(info.value)
    store.close()
