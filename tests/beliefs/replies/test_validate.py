"""One belief rule, refused the same way at every door .

A belief is one finite, non-negative number per action summing to 1 within 1e-6. Each
bad vector below is refused by the validator itself, by a recording file, by a store
write, by a store read, by a JSON Lines import, and, as a live answer, turned into an
abstention ("error"/"abstained") rather than an "ok" row.
"""

from __future__ import annotations

import io
import json
import math
import sqlite3
from collections.abc import Sequence

import httpx
import numpy as np
import pytest

from amuled_ma.beliefs import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.beliefs.replies.validate import (
    SUM_TOLERANCE,
    InvalidBeliefError,
    check_belief,
    check_beliefs,
    checked_result,
    validate_belief,
)
from amuled_ma.beliefs.sources.replay import ReplaySource
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.interchange import export_jsonl, import_jsonl
from amuled_ma.beliefs.store.keys import request_key
from amuled_ma.beliefs.store.rows import BeliefStoreError
from amuled_ma.errors import AmuledError, ScenarioError

MILK = ("up", "down", "left", "right")
IDENT = {"source": "nan-bot"}

# (id, values, the reason the message must give) for a task of 4 actions
BAD = [
    ("nan", [math.nan, 0.0, 0.0, 0.0], "holds nan at index 0"),
    ("negative", [-1.0, 0.0, 0.0, 2.0], "negative value -1.0 at index 0"),
    ("all-zero", [0.0, 0.0, 0.0, 0.0], "sums to 0"),
    ("too-short", [1.0], "has 1 value(s), expected 4"),
    ("overflow", [1e308, 1e308, 0.0, 0.0], "sums to inf (the values overflow)"),
    ("inf", [math.inf, 0.0, 0.0, 0.0], "holds inf at index 0"),
    ("too-long", [0.5, 0.5, 0.0, 0.0, 0.0], "has 5 value(s), expected 4"),
]
BAD_IDS = [b[0] for b in BAD]


def strict_loads(text: str):
    """json.loads that refuses NaN/Infinity, as any standard JSON reader does."""

    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


# -- the validator -------------------------------------------------------------------


@pytest.mark.parametrize(("name", "values", "reason"), BAD, ids=BAD_IDS)
def test_validator_refuses_each_bad_vector(name, values, reason):
    belief, why = check_belief(values, 4)
    assert belief is None and reason in why
    with pytest.raises(InvalidBeliefError) as info:
        validate_belief(values, 4, where="somewhere.json: states[3]")
    message = str(info.value)
    assert isinstance(info.value, AmuledError)
    assert message.startswith("somewhere.json: states[3]: invalid belief")
    assert reason in message and "summing to 1" in message  # what was found, the rule


@pytest.mark.parametrize(
    "values",
    [[True, False, False, False], ["0.5", "0.5", 0, 0], [[0.5, 0.5], [0, 0]], "up", None, 0.5],
)
def test_validator_refuses_what_is_not_a_list_of_numbers(values):
    belief, why = check_belief(values, 4)
    assert belief is None and why


def test_tolerance_and_exact_renormalisation():
    assert SUM_TOLERANCE == 1e-6
    # within 1e-6 of 1: accepted and divided by the sum
    inside = [0.5 + 9e-7, 0.5, 0.0, 0.0]
    belief = validate_belief(inside, 4, where="x")
    np.testing.assert_allclose(belief, np.array(inside) / (1.0 + 9e-7), rtol=1e-15)
    assert abs(belief.sum() - 1.0) <= 2.3e-16
    # within float64 rounding of 1 it is kept bit for bit (so the check is idempotent)
    assert sum([0.7, 0.1, 0.1, 0.1]) == 0.9999999999999999
    assert validate_belief([0.7, 0.1, 0.1, 0.1], 4, where="x").tolist() == [0.7, 0.1, 0.1, 0.1]
    again = validate_belief(belief, 4, where="x")
    assert again.tolist() == belief.tolist()
    # just outside: refused, and the message gives the sum found
    belief, why = check_belief([0.5 + 2e-6, 0.5, 0.0, 0.0], 4)
    assert belief is None and why.startswith("sums to 1.0000019") and "tolerance 1e-06" in why
    # an LLM's [0.3, 0.3, 0.3] is not a belief: the parser repairs it on purpose
    assert check_belief([0.3, 0.3, 0.3], 3)[0] is None
    # a rule's scores: any positive finite sum, divided by it
    np.testing.assert_array_equal(check_belief([0, 2, 0, 0], 4, scores=True)[0], [0, 1, 0, 0])
    assert check_belief([-1, 2, 0, 0], 4, scores=True)[0] is None
    assert check_belief([1e308, 1e308, 0, 0], 4, scores=True)[0] is None


def test_vectorised_check_agrees_with_the_single_one():
    rows = np.array([v for _, v, _ in BAD if len(v) == 4] + [[0.25] * 4, [0.0, 0.0, 1.0, 0.0]])
    out, reasons = check_beliefs(rows)
    assert reasons[:-2] == [check_belief(v, 4)[1] for v in rows[:-2]]
    assert reasons[-2:] == [None, None]
    np.testing.assert_array_equal(out[-2:], [[0.25] * 4, [0.0, 0.0, 1.0, 0.0]])


# -- door 1: recording files ---------------------------------------------------------


def write_recording(path, states, actions=MILK):
    """A recording in the authors' format (see ../shared/amuled-recordings/README.md)."""
    data = {
        "task": "FindMilk",
        "model": "test",
        "clusters": ["consequentialist", "deontologist", "virtue", "care", "social justice"],
        "actions": list(actions),
        "obs_layout": [],
        "states": states,
    }
    path.write_text(json.dumps(data))  # json.dumps writes NaN/Infinity for nan/inf
    return path


def state(x, care, moral=(0.0, 0.0, 0.0, 1.0)):
    return {
        "obs": [float(x), 0.0],
        "beliefs": {"virtue": [0.25] * 4, "care": care},
        "moral_agent": list(moral),
        "error": False,
    }


@pytest.mark.parametrize(("name", "values", "reason"), BAD, ids=BAD_IDS)
def test_recording_with_a_bad_belief_is_refused(tmp_path, name, values, reason):
    path = write_recording(tmp_path / "rec.json", [state(0, [1, 0, 0, 0]), state(1, values)])
    with pytest.raises(ScenarioError) as info:
        ReplaySource(path)
    message = str(info.value)
    assert str(path) in message and "refusing to load the recording: 1 invalid belief" in message
    assert "states[1].beliefs['care'] (obs [1.0, 0.0])" in message and reason in message
    assert "correct or remove these entries" in message


def test_recording_refusal_lists_the_first_five_and_counts_all(tmp_path):
    states = [state(i, [0, 0, 0, 0], moral=[math.nan, 0, 0, 1]) for i in range(40)]
    path = write_recording(tmp_path / "rec.json", states)
    with pytest.raises(ScenarioError) as info:
        ReplaySource(path)
    message = str(info.value)
    assert "80 invalid belief(s)" in message and "the first 5:" in message
    assert message.count("states[") == 5
    assert "states[0].moral_agent" in message and "states[2].beliefs['care']" in message


def test_deeply_nested_recording_is_a_clear_error(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text('{"task": "FindMilk", "states": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(ScenarioError, match=r"deep\.json: cannot read recording: not JSON "):
        ReplaySource(path)


def test_null_beliefs_are_not_recorded_not_a_crash(tmp_path):
    # the fused-only recording (driving-gpt-4o-mini.json) has "beliefs": null
    fused_only = {"obs": [2.0, 0.0], "beliefs": None, "moral_agent": None, "error": False}
    path = write_recording(tmp_path / "rec.json", [state(0, [1, 0, 0, 0]), fused_only])
    source = ReplaySource(path, miss_policy="uniform")
    care = BeliefRequest("findmilk", "care", (2.0, 0.0), MILK)
    (result,) = source.beliefs([care])
    assert result.status == "replay_miss" and source.misses == 1


# -- door 2: store writes ------------------------------------------------------------


def req(i=1, cluster="care"):
    return BeliefRequest("findmilk", cluster, (float(i), 2.0), MILK, (("user", f"state {i}"),))


@pytest.mark.parametrize(("name", "values", "reason"), BAD, ids=BAD_IDS)
@pytest.mark.parametrize("status", ["ok", "repaired", "abstained"])
def test_store_refuses_to_write_a_bad_belief(tmp_path, name, values, reason, status):
    with BeliefStore(tmp_path / "s.sqlite") as store:
        key = request_key(IDENT, req())
        good = (request_key(IDENT, req(2)), IDENT, req(2), BeliefResult(np.eye(4)[0], "ok", "x"))
        bad = BeliefResult(np.asarray(values, dtype=np.float64), status, "nan-bot")
        with pytest.raises(BeliefStoreError) as info:
            store.put_many([good, (key, IDENT, req(), bad)])
        message = str(info.value)
        assert f"s.sqlite: refusing to write row {key}" in message and reason in message
        assert f"status {status!r}, source 'nan-bot'" in message
        assert len(store) == 0  # nothing of the batch was written


# -- door 3: store reads -------------------------------------------------------------


def raw_store(tmp_path, belief_text, status="ok"):
    """A store with one good row and one row whose belief column is ``belief_text``."""
    path = tmp_path / "s.sqlite"
    with BeliefStore(path) as store:
        for i in (1, 2):
            r = BeliefResult(np.array([0.1, 0.2, 0.3, 0.4]), "ok", "nan-bot")
            store.put_many([(request_key(IDENT, req(i)), IDENT, req(i), r)])
    key = request_key(IDENT, req(2))
    conn = sqlite3.connect(path)  # as a hand edit or another program would
    conn.execute(
        "UPDATE beliefs SET belief = ?, status = ? WHERE key = ?", (belief_text, status, key)
    )
    conn.commit()
    conn.close()
    return path, key


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("not json", "column 'belief' is not JSON"),
        ("[" * 100_000 + "]" * 100_000, "nested deeper than Python's JSON reader"),
        ("[NaN, 0, 0, 0]", "holds nan at index 0"),
        ("[-1, 0, 0, 2]", "negative value -1.0"),
        ("[0, 0, 0, 0]", "sums to 0"),
        ("[1.0]", "has 1 value(s), expected 4"),
        ("[1e308, 1e308, 0, 0]", "sums to inf"),
    ],
    ids=["not-json", "deep", "nan", "negative", "zero", "short", "overflow"],
)
def test_a_damaged_row_is_our_error_at_every_read(tmp_path, text, found):
    path, key = raw_store(tmp_path, text)
    with BeliefStore(path) as store:
        reads = [
            lambda: store.lookup([key]),
            lambda: store.get(key),
            lambda: list(store.iter_rows()),
            lambda: export_jsonl(store, io.StringIO()),
        ]
        for read in reads:
            with pytest.raises(BeliefStoreError) as info:
                read()
            message = str(info.value)
            assert f"{path}: row {key}" in message and found in message
            assert f"DELETE FROM beliefs WHERE key = '{key}'" in message  # the fix
        # the good row is still served
        assert list(store.lookup([request_key(IDENT, req(1))]))


# -- door 4: JSON Lines import and export ---------------------------------------------


def row_json(values, status="ok", i=1):
    r = req(i)
    return {
        "key": request_key(IDENT, r),
        "source": "nan-bot",
        "identity": IDENT,
        "task": r.task,
        "cluster": r.cluster,
        "obs": list(r.obs),
        "actions": list(MILK),
        "messages": [list(m) for m in r.messages],
        "raw": None,
        "belief": values,
        "status": status,
    }


@pytest.mark.parametrize(("name", "values", "reason"), BAD, ids=BAD_IDS)
def test_import_refuses_each_bad_belief(tmp_path, name, values, reason):
    text = json.dumps(row_json([1.0, 0.0, 0.0, 0.0], i=3)) + "\n" + json.dumps(row_json(values))
    with BeliefStore(tmp_path / "s.sqlite") as store:
        with pytest.raises(BeliefStoreError) as info:
            import_jsonl(store, io.StringIO(text + "\n"), name="dump.jsonl")
        message = str(info.value)
        assert message.startswith("dump.jsonl:2")
        if "nan" in name or name == "inf":  # json.dumps wrote a NaN/Infinity literal
            assert "not JSON" in message and "is not standard JSON" in message
        else:
            assert f"(key {row_json(values)['key']})" in message and reason in message
        assert len(store) == 0


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_import_refuses_non_standard_json_anywhere(tmp_path, literal):
    line = json.dumps(row_json([1.0, 0.0, 0.0, 0.0])).replace('"raw": null', f'"raw": {literal}')
    match = rf"f\.jsonl:1: not JSON \({literal} is not"
    with BeliefStore(tmp_path / "s.sqlite") as store, pytest.raises(BeliefStoreError, match=match):
        import_jsonl(store, io.StringIO(line), name="f.jsonl")


def test_import_refuses_deep_nesting_and_non_objects(tmp_path):
    deep = '{"key": ' + "[" * 100_000 + "]" * 100_000 + "}"
    with BeliefStore(tmp_path / "s.sqlite") as store:
        with pytest.raises(BeliefStoreError, match=r"d\.jsonl:2: not JSON \(nested deeper"):
            import_jsonl(store, io.StringIO("\n" + deep + "\n"), name="d.jsonl")
        with pytest.raises(BeliefStoreError, match=r"d\.jsonl:1: expected a JSON object"):
            import_jsonl(store, io.StringIO("[1, 2]\n"), name="d.jsonl")


def test_export_writes_standard_json_only(tmp_path):
    with BeliefStore(tmp_path / "s.sqlite") as store:
        r = BeliefResult(
            np.array([0.7, 0.1, 0.1, 0.1]),
            "ok",
            "nan-bot",
            latency_s=0.5,
            extra={"score": math.nan, "nested": {"big": math.inf}},
        )
        store.put_many([(request_key(IDENT, req()), IDENT, req(), r)])
        buf = io.StringIO()
        assert export_jsonl(store, buf) == 1
    row = strict_loads(buf.getvalue())  # no NaN/Infinity anywhere in the line
    assert row["belief"] == [0.7, 0.1, 0.1, 0.1]
    assert row["extra"] == {"score": "nan", "nested": {"big": "inf"}}


# -- door 5: live answers (any source, through CachedSource) ----------------------------


class NanBot(BeliefSource):
    """A plug-in source that answers whatever it is given, always with status "ok"."""

    name = "nan-bot"
    needs_messages = False

    def __init__(self, answer):
        self.answer = answer
        self.calls = 0

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        self.calls += 1
        return [
            BeliefResult(np.asarray(self.answer, dtype=np.float64), "ok", self.name)
            for _ in requests
        ]

    def identity(self):
        return dict(IDENT)


@pytest.mark.parametrize(("name", "values", "reason"), BAD, ids=BAD_IDS)
def test_an_invalid_live_answer_is_stored_and_returned_as_error(tmp_path, name, values, reason):
    bot = NanBot(values)
    with BeliefStore(tmp_path / "s.sqlite") as store:
        cached = CachedSource(bot, store)
        (result,) = cached.beliefs([req()])
        assert result.status == "error"
        np.testing.assert_array_equal(result.belief, [0.25] * 4)
        assert (
            reason in result.extra["error"]
            and "nan-bot gave an invalid belief" in (result.extra["error"])
        )
        assert result.extra["invalid_status"] == "ok"
        assert cached.stats.invalid == 1
        row = store.get(request_key(IDENT, req()), cacheable_only=False)
        assert row.status == "error" and row.belief.tolist() == [0.25] * 4
        assert reason in row.extra["error"]
        # never served: the next run asks again
        cached.beliefs([req()])
        assert bot.calls == 2


def test_checked_result_keeps_a_valid_answer_and_the_reason_of_a_failure():
    ok = checked_result(BeliefResult(np.array([0.5 + 5e-7, 0.5, 0, 0]), "ok", "s"), 4)
    assert ok.status == "ok" and ok.belief.sum() == pytest.approx(1.0, abs=1e-15)
    failed = BeliefResult(np.array([math.nan] * 4), "timeout", "s", extra={"error": "slow"})
    checked_result(failed, 4)
    assert failed.status == "timeout" and failed.extra["error"] == "slow"
    assert failed.belief.tolist() == [0.25] * 4 and failed.extra["invalid_belief"] == (
        "[nan, nan, nan, nan]"
    )


def test_ollama_never_answers_ok_with_an_invalid_belief(monkeypatch):
    """The Ollama door: replies that give an invalid belief are abstentions.

    Real replies first (the parser refuses them itself); then a parser that lets an
    invalid vector through as "ok" (standing in for a parser bug) must still end as
    "abstained", after the documented re-ask.
    """
    from amuled_ma.beliefs.replies.parsing import ParsedBelief
    from amuled_ma.beliefs.sources import ollama as ollama_module

    replies = iter(
        [
            '{"reasoning": "r", "0": NaN, "1": 0, "2": 0, "3": 1}',
            '{"reasoning": "r", "0": 1e308, "1": 1e308, "2": 0, "3": 0}',
        ]
        * 4
    )

    def server(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/api/version":
            return httpx.Response(200, json={"version": "0.0.0-fake"})
        if request.url.path == "/api/tags":
            return httpx.Response(200, json={"models": [{"model": "m:latest", "digest": "d"}]})
        content = next(replies)
        message = {"role": "assistant", "content": content}
        return httpx.Response(200, json={"model": "m", "message": message, "done": True})

    source = ollama_module.OllamaSource(
        "m", host="http://fake:11434", transport=httpx.MockTransport(server), parse_retries=1
    )
    request = BeliefRequest("findmilk", "care", (1.0,), MILK, (("user", "state"),))
    for result in source.beliefs([request, request]) + source.beliefs([request]):
        assert result.status not in ("ok", "repaired")
        assert check_belief(result.belief, 4)[0] is not None

    def lenient(text, action_names, *, structured=False):
        return ParsedBelief(np.array([math.nan, 0.0, 0.0, 1.0]), "ok")

    monkeypatch.setattr(ollama_module, "parse_belief", lenient)
    before = source.stats.parse_retries
    (result,) = source.beliefs([BeliefRequest("findmilk", "virtue", (2.0,), MILK, (("u", "s"),))])
    assert result.status == "abstained" and result.belief.tolist() == [0.25] * 4
    assert "the reply gave an invalid belief: it holds nan at index 0" in result.extra["error"]
    assert result.extra["invalid_belief"] == "[nan, 0.0, 0.0, 1.0]"
    assert source.stats.parse_retries == before + 1  # re-asked like any abstention
    source.close()


@pytest.mark.parametrize(("name", "values", "reason"), BAD, ids=BAD_IDS)
def test_rule_and_script_answers_are_checked(name, values, reason):
    from amuled_ma.beliefs import RulesSource, ScriptedSource

    requests = [req(1), req(2)]  # two requests: the rules source's batched path first
    for source in (
        RulesSource(lambda task, obs: values),
        ScriptedSource({"*": values}),
        ScriptedSource(lambda request: values),
    ):
        for result in source.beliefs(requests):
            assert result.status == "error", source
            assert result.belief.tolist() == [0.25] * 4
            assert reason in result.extra["error"]


def test_replay_fallback_answers_are_checked(tmp_path):
    path = write_recording(tmp_path / "rec.json", [state(0, [1, 0, 0, 0])])
    source = ReplaySource(path, miss_policy="fallback", fallback=NanBot([math.nan, 0, 0, 1]))
    (result,) = source.beliefs([BeliefRequest("findmilk", "care", (9.0, 0.0), MILK)])
    assert result.status == "error" and result.extra["replay_miss"] is True
    assert result.belief.tolist() == [0.25] * 4 and "holds nan" in result.extra["error"]
