"""The person's route: "state k of n", the state as a picture, the full prompt on request,
actions by name; driven by a scripted stdin."""

from __future__ import annotations

import io

from scenario_feedback import make_feedback

from amuled_ma.beliefs import BeliefRequest
from amuled_ma.beliefs.sources.terminal import TerminalSource, action_by_name, parse_answer
from amuled_ma.deliberation.summaries import nested_sources
from amuled_ma.scenario import scenario_from_dict

MILK = ("up", "down", "left", "right")
#: robot (2, 3), milk (7, 7), nearest crying baby (2, 2), nearest sleeping baby (1, 1)
OBS = (2.0, 3.0, 7.0, 7.0, 2.0, 2.0, 1.0, 1.0)
PROMPT = "You are tasked with finding milk ... Behave as an agent that assigns credence 1 to care."
CHAT = (("system", "You are a moral agent."), ("user", PROMPT))


def _ask(lines: str, requests: list[BeliefRequest], expected: int | None, attempts: int = 1):
    out = io.StringIO()
    person = TerminalSource(person="ann", attempts=attempts, stdin=io.StringIO(lines), stdout=out)
    person.expected = expected
    results = person.beliefs(requests)
    return results, out.getvalue()


def test_state_k_of_n_across_batches_with_the_grid_and_the_prompt_on_request() -> None:
    out = io.StringIO()
    typed = io.StringIO("prompt\nUP\nri\nLeft\n")  # the person's lines, in order
    person = TerminalSource(person="ann", attempts=1, stdin=typed, stdout=out)
    person.expected = 3
    first = person.beliefs([BeliefRequest("findmilk", "care", OBS, MILK, CHAT)])
    moved = (3.0, 3.0, *OBS[2:])
    rest = person.beliefs(
        [
            BeliefRequest("findmilk", "care", moved, MILK, CHAT),
            BeliefRequest("findmilk", "care", (4.0, 3.0, *OBS[2:]), MILK, CHAT),
        ]
    )
    text = out.getvalue()
    # k counts every state asked of this person, n is the total the builder gave
    assert "state 1 of 3 ==" in text and "state 2 of 3 ==" in text and "state 3 of 3 ==" in text
    # the grid, y up: the robot R at (2, 3), the crying baby C below it, milk M top right
    assert "  y=7 . . . . . . . M\n" in text
    assert "  y=3 . . R . . . . .\n" in text
    assert "  y=2 . . C . . . . .\n" in text
    assert "  y=1 . z . . . . . .\n" in text
    # the raw prompt is not shown until asked for, then shown once; "prompt" is no attempt
    assert text.count(PROMPT) == 1
    assert [r.belief.tolist() for r in first + rest] == [
        [1.0, 0.0, 0.0, 0.0],  # UP
        [0.0, 0.0, 0.0, 1.0],  # ri -> right
        [0.0, 0.0, 1.0, 0.0],  # Left
    ]


def test_without_a_known_total_it_says_what_the_batch_holds() -> None:
    requests = [BeliefRequest("findmilk", "care", (float(i), *OBS[1:]), MILK, CHAT) for i in (1, 2)]
    results, text = _ask("0\n1\n", requests, expected=None)
    assert "state 1 (1 more now) ==" in text and "state 2 ==" in text
    assert [r.status for r in results] == ["ok", "ok"]


def test_action_names_and_prefixes() -> None:
    assert action_by_name("DOWN", MILK) == (1, [])
    assert action_by_name(" d ", MILK) == (1, [])
    assert action_by_name("straight", ("straight", "right", "left")) == (0, [])
    # an unambiguous start only; a whole name wins over a longer one it starts
    assert action_by_name("l", ("left", "lift")) == (None, ["left", "lift"])
    assert action_by_name("go", ("go", "goal")) == (0, [])
    assert action_by_name("north", MILK) == (None, [])
    assert action_by_name("le", ("left", "lift")) == (0, [])
    belief, why = parse_answer("L", 2, ("left", "lift"))
    assert belief is None and why is not None
    assert why.startswith("found 'L', the start of left and lift; expected 2 non-negative")
    assert "an action name (left, lift)" in why
    belief, why = parse_answer("north", 4, MILK)
    assert belief is None and why is not None and why.startswith("found 'north', not a number")
    # numbers keep their meaning (1e-1 has a letter but names no action)
    belief, _ = parse_answer("1e-1 0 0 0", 4, MILK)
    assert belief is not None and belief.tolist() == [1.0, 0.0, 0.0, 0.0]


def test_driving_lanes_picture() -> None:
    # on lane 4 (one-hot last): a car 2 ahead on the left lane, a grandma 3 ahead on yours,
    # no right lane (-2)
    obs = (-1.0, 3.0, 2.0, -1.0, -2.0, -2.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    chat = (("user", "You are a driving agent ..."),)
    request = BeliefRequest("driving", "care", obs, ("straight", "right", "left"), chat)
    results, text = _ask("s\n", [request], expected=1)
    assert results[0].belief.tolist() == [1.0, 0.0, 0.0]  # "s": straight, not skip
    assert "you drive on lane 4 (lanes 0..4)" in text
    assert "left lane   car 2 ahead, no grandma" in text
    assert "your lane   no car, grandma 3 ahead" in text
    assert "right lane  none (road edge)" in text


def test_the_builder_tells_the_person_the_budget(tmp_path) -> None:
    """budget = 12 distinct states, the person answers for two agents: 24 questions."""
    scenario = scenario_from_dict(
        {
            "task": {"name": "findmilk"},
            "feedback": {
                "source": "rules",
                "store": str(tmp_path / "beliefs.sqlite"),
                "distill": {"enabled": True, "budget": 12},
                "agents": {
                    "care": {"source": "terminal", "person": "ann"},
                    "virtue": {"source": "terminal", "person": "ann"},
                },
            },
        }
    )
    feedback = make_feedback("amuled", scenario, tmp_path / "run", state_dir=tmp_path / "ft")
    people = [s for s in nested_sources(feedback.source) if isinstance(s, TerminalSource)]
    assert [p.expected for p in people] == [24]
    feedback.close()
