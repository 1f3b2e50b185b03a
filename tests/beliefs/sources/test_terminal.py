"""The terminal source: a person's typed beliefs, through a real stdin and in process."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from amuled_ma.beliefs import BeliefRequest, make_source
from amuled_ma.beliefs.sources.terminal import TerminalSource, parse_answer
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.errors import ScenarioError

MILK = ("up", "down", "left", "right")
REPO = Path(__file__).resolve().parents[3]

#: A tiny program: a TerminalSource on the real sys.stdin answers two requests and
#: prints, on stdout, each result's status, belief and reason.
PROGRAM = textwrap.dedent(
    """
    import json
    from amuled_ma.beliefs import BeliefRequest
    from amuled_ma.beliefs.sources.terminal import TerminalSource

    actions = ("up", "down", "left", "right")
    chat = (("system", "You are a moral agent."),
            ("user", "The robot is at (1, 2); a baby cries at (2, 2)."))
    requests = [
        BeliefRequest("findmilk", "care", (1.0, 2.0), actions, chat),
        BeliefRequest("findmilk", "care", (3.0, 4.0), actions, chat),
    ]
    results = TerminalSource(person="ann").beliefs(requests)
    print(json.dumps([
        {"status": r.status, "belief": r.belief.tolist(), "error": r.extra.get("error")}
        for r in results
    ]))
    """
)


def run_program(stdin: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", PROGRAM],
        input=stdin,
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
        check=True,
    )


def req(obs=(1.0, 2.0), cluster="care", messages=()) -> BeliefRequest:
    return BeliefRequest("findmilk", cluster, obs, MILK, messages)


def test_answers_typed_on_a_real_stdin():
    done = run_program("0.5 0.5 0 0\nskip\n")
    answers = json.loads(done.stdout)
    assert answers == [
        {"status": "ok", "belief": [0.5, 0.5, 0.0, 0.0], "error": None},
        {"status": "abstained", "belief": [0.25, 0.25, 0.25, 0.25], "error": "skipped by ann"},
    ]
    # the person saw each state prompt, the actions and the prompt line (on stderr)
    assert done.stderr.count("The robot is at (1, 2); a baby cries at (2, 2).") == 2
    assert "state 1 (1 more now) ==" in done.stderr and "state 2 ==" in done.stderr
    assert "actions: 0: up | 1: down | 2: left | 3: right" in done.stderr
    assert done.stderr.count("belief> ") == 2


def test_a_closed_stdin_abstains_at_once_and_never_hangs():
    start = time.perf_counter()
    done = run_program("")
    answers = json.loads(done.stdout)
    assert [a["status"] for a in answers] == ["abstained", "abstained"]
    assert all("input of the terminal source (ann) has ended" in a["error"] for a in answers)
    assert time.perf_counter() - start < 60
    # asked once; the second state is abstained without being shown
    assert done.stderr.count("belief> ") == 1


def test_an_action_index_is_a_one_hot_belief():
    out = io.StringIO()
    source = TerminalSource(stdin=io.StringIO("2\n"), stdout=out)
    (result,) = source.beliefs([req()])
    assert result.status == "ok" and result.belief.tolist() == [0.0, 0.0, 1.0, 0.0]
    assert result.raw == "2"
    assert "observation: 1, 2" in out.getvalue()  # no chat: the observation is shown


def test_invalid_lines_are_refused_and_asked_again():
    lines = "abc\n0.5 0.5\n-1 1 0 0\n7\n1, 1, 0, 0\n"
    out = io.StringIO()
    source = TerminalSource(attempts=5, stdin=io.StringIO(lines), stdout=out)
    (result,) = source.beliefs([req()])
    assert result.status == "ok" and result.belief.tolist() == [0.5, 0.5, 0.0, 0.0]
    assert result.extra["attempts"] == 5
    shown = out.getvalue()
    assert shown.count("not read:") == 4
    assert "found 'abc', not a number" in shown
    assert "has 2 value(s), expected 4" in shown
    assert "negative value -1.0" in shown
    assert "found the action index 7, out of range" in shown
    assert source.stats["invalid"] == 4 and source.stats["answered"] == 1


def test_an_answer_of_thousands_of_digits_is_asked_again_with_a_short_reason():
    # int() of more than 4,300 digits raises ValueError; float() of them is inf
    lines = "9" * 5000 + "\n" + " ".join(["7" * 2000] * 4) + "\n" + "x" * 5000 + "\n1\n"
    out = io.StringIO()
    source = TerminalSource(attempts=4, stdin=io.StringIO(lines), stdout=out)
    (result,) = source.beliefs([req()])
    assert result.status == "ok" and result.belief.tolist() == [0.0, 1.0, 0.0, 0.0]
    shown = out.getvalue()
    assert "found an action index of 5,000 digits, out of range" in shown
    assert "... (2,000 characters), not a finite number" in shown
    assert "... (5,000 characters), not a number" in shown
    assert max(len(line) for line in shown.splitlines()) < 1000  # reasons quote 40 characters
    assert source.stats["invalid"] == 3


def test_too_many_invalid_lines_abstain_and_the_next_state_is_asked():
    source = TerminalSource(
        attempts=2, stdin=io.StringIO("x\nnan 0 0 1\n3\n"), stdout=io.StringIO()
    )
    first, second = source.beliefs([req((1.0,)), req((2.0,))])
    assert first.status == "abstained"
    assert first.extra["error"] == "2 invalid answer(s) from human; the last: 'nan 0 0 1'"
    assert np.allclose(first.belief, 0.25)
    assert second.status == "ok" and second.belief.tolist() == [0.0, 0.0, 0.0, 1.0]


def test_end_of_input_mid_batch_abstains_the_rest_without_reading_again():
    class Counting(io.StringIO):
        reads = 0

        def readline(self, *args):
            Counting.reads += 1
            return super().readline(*args)

    source = TerminalSource(stdin=Counting("1\n"), stdout=io.StringIO())
    results = source.beliefs([req((1.0,)), req((2.0,)), req((3.0,))])
    assert [r.status for r in results] == ["ok", "abstained", "abstained"]
    assert Counting.reads == 2 and source.eof
    assert source.stats["eof"] == 2


def test_identical_requests_in_a_batch_are_asked_once():
    out = io.StringIO()
    source = TerminalSource(stdin=io.StringIO("0\n"), stdout=out)
    results = source.beliefs([req(), req()])
    assert [r.belief.tolist() for r in results] == [[1.0, 0.0, 0.0, 0.0]] * 2
    assert results[0] is not results[1]
    assert out.getvalue().count("belief> ") == 1


def test_answers_are_stored_so_a_person_is_asked_once_per_state(tmp_path):
    store = BeliefStore(tmp_path / "beliefs.sqlite")
    chat = (("system", "s"), ("user", "a state"))
    batch = [req((1.0,), messages=chat), req((2.0,), messages=chat), req((3.0,), messages=chat)]
    first = CachedSource(
        TerminalSource(person="ann", stdin=io.StringIO("3\nskip\n0.2 0.2 0.2 0.4\n")), store
    )
    assert [r.status for r in first.beliefs(batch)] == ["ok", "abstained", "ok"]

    # a resumed run: the two answers come from the store; only the skipped state is asked
    out = io.StringIO()
    second = CachedSource(
        TerminalSource(person="ann", stdin=io.StringIO("1\n"), stdout=out),
        BeliefStore(tmp_path / "beliefs.sqlite"),
    )
    results = second.beliefs(batch)
    assert [r.status for r in results] == ["ok", "ok", "ok"]
    assert [r.cached for r in results] == [True, False, True]
    assert results[0].belief.tolist() == [0.0, 0.0, 0.0, 1.0]
    assert results[1].belief.tolist() == [0.0, 1.0, 0.0, 0.0]
    assert np.allclose(results[2].belief, [0.2, 0.2, 0.2, 0.4])
    assert out.getvalue().count("belief> ") == 1

    # another person's answers are kept apart (the person is in the store key)
    bob = CachedSource(TerminalSource(person="bob", stdin=io.StringIO("")), store)
    assert [r.status for r in bob.beliefs(batch[:1])] == ["abstained"]


@pytest.mark.parametrize(
    ("line", "belief"),
    [
        ("0.7 0.1 0.1 0.1", [0.7, 0.1, 0.1, 0.1]),
        ("0.7,0.1,0.1,0.1", [0.7, 0.1, 0.1, 0.1]),
        ("  1 1 1 1  ", [0.25, 0.25, 0.25, 0.25]),
        ("3", [0.0, 0.0, 0.0, 1.0]),
        ("SKIP", None),
    ],
)
def test_parse_answer_reads(line, belief):
    got, reason = parse_answer(line, 4)
    assert reason is None
    assert (got is None) if belief is None else np.allclose(got, belief)


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("", "empty line"),
        ("inf 0 0 0", "not a finite number"),
        ("0 0 0 0", "sums to 0"),
        ("-1", "action index -1, out of range"),
        ("1 2 3 4 5", "has 5 value(s)"),
    ],
)
def test_parse_answer_refuses(line, why):
    got, reason = parse_answer(line, 4)
    assert got is None and why in reason
    assert "expected 4 non-negative numbers" in reason


def test_made_by_kind_with_its_options_checked():
    source = make_source("terminal", person="ann", attempts=2)
    assert source.identity() == {"source": "terminal", "person": "ann"}
    assert source.needs_messages is True
    with pytest.raises(ScenarioError, match=r"attempts expects an integer in \[1, 100\]"):
        TerminalSource(attempts=0)
