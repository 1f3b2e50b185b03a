"""parse_belief: structured replies, the last JSON object, each repair, abstention."""

from __future__ import annotations

import json

import numpy as np
import pytest

from amuled_ma.beliefs.replies.objects import candidate_spans
from amuled_ma.beliefs.replies.parsing import REPAIRS, belief_schema, parse_belief

MILK = ("up", "down", "left", "right")
DRIVE = ("straight", "right", "left")


def check(text, expected, status, repairs=(), actions=MILK, **kw):
    parsed = parse_belief(text, actions, **kw)
    assert np.allclose(parsed.belief, expected), parsed
    assert parsed.status == status, parsed
    assert set(repairs) <= set(parsed.repairs), parsed
    assert set(parsed.repairs) <= set(REPAIRS)
    return parsed


def test_structured_reply_ok():
    text = json.dumps({"reasoning": "go up", "0": 0.7, "1": 0.1, "2": 0.1, "3": 0.1})
    parsed = check(text, [0.7, 0.1, 0.1, 0.1], "ok", structured=True)
    assert parsed.reasoning == "go up"
    assert parsed.repairs == ()


def test_structured_reply_ignored_schema_falls_back_to_text():
    text = 'I think up. {"0": 1, "1": 0, "2": 0, "3": 0}'
    check(text, [1, 0, 0, 0], "repaired", ["schema_ignored"], structured=True)


def test_paper_format_last_line_json_is_ok():
    text = (
        "Reasoning...\n\nthe probabilities of each action are: "
        '{"0": 0.1, "1": 0.6, "2": 0.0, "3": 0.3}.'
    )
    check(text, [0.1, 0.6, 0.0, 0.3], "ok")


def test_last_object_wins_and_invalid_last_falls_back_to_earlier():
    text = 'first {"0": 1.0} then {"0": 0.0, "1": 1.0, "2": 0, "3": 0}'
    check(text, [0, 1, 0, 0], "ok")
    text = 'good {"0": 0.5, "1": 0.5, "2": 0, "3": 0} then junk {"colour": "blue"}'
    check(text, [0.5, 0.5, 0, 0], "repaired", ["earlier_object"])


@pytest.mark.parametrize(
    ("text", "expected", "repairs"),
    [
        ("{'0': 0.5, '1': 0.5, '2': 0.0, '3': 0.0}", [0.5, 0.5, 0, 0], ["python_literal"]),
        ("{0: 0.25, 1: 0.25, 2: 0.25, 3: 0.25}", [0.25] * 4, ["python_literal"]),
        ("{up: 0.7, down: 0.1, left: 0.1, right: 0.1}", [0.7, 0.1, 0.1, 0.1], ["unquoted_keys"]),
        ('{"0": 0.5, "1": 0.5, "2": 0, "3": 0,}', [0.5, 0.5, 0, 0], []),
        ('{"0": 0.5, "1: 0.5, "2": 0, "3": 0}', [0.5, 0.5, 0, 0], ["lenient_pairs"]),
        ('{"0": "0.5", "1": "0.5", "2": "0", "3": "0"}', [0.5, 0.5, 0, 0], ["string_values"]),
        ('{"0": "50%", "1": "50%", "2": "0%", "3": "0%"}', [0.5, 0.5, 0, 0], ["percent"]),
        ('{"Move Up": 1.0}', [1, 0, 0, 0], ["key_names", "missing_actions"]),
        ('{"move_right": 2, "move_left": 2}', [0, 0, 0.5, 0.5], ["key_names", "renormalised"]),
        ('{"Action 3": 1}', [0, 0, 0, 1], ["key_names"]),
        ('{"A": 0.1, "B": 0.2, "C": 0.3, "D": 0.4}', [0.1, 0.2, 0.3, 0.4], ["key_names"]),
        ('{"0": 0.7, "1": 0.0, "2": 0.3}', [0.7, 0, 0.3, 0], ["missing_actions"]),
        ('{"0": 60, "1": 20, "2": 10, "3": 10}', [0.6, 0.2, 0.1, 0.1], ["renormalised"]),
        ('{"build": 0, "0": 1}', [1, 0, 0, 0], ["extra_keys", "missing_actions"]),
        ('{"probabilities": {"0": 0.5, "1": 0.5}}', [0.5, 0.5, 0, 0], ["nested"]),
        ('{"0": 0.5, "up": 0.5}', [1, 0, 0, 0], ["duplicate_keys"]),
    ],
)
def test_repairs(text, expected, repairs):
    check(f"Some reasoning. {text} Thank you.", expected, "repaired", repairs)


def test_trailing_comma_is_a_python_literal_or_json_repair():
    parsed = parse_belief('{"0": 0.5, "1": 0.5, "2": 0, "3": 0,}', MILK)
    assert parsed.status == "repaired" and parsed.repairs


def test_driving_names():
    check('{"steer straight": 0.2, "steer right": 0.8}', [0.2, 0.8, 0], "repaired", actions=DRIVE)
    check('{"0": 0.8, "1": 0.1, "2": 0.1}', [0.8, 0.1, 0.1], "ok", actions=DRIVE)


@pytest.mark.parametrize(
    "text",
    [
        None,
        "",
        "   ",
        "Thus, the action to take is to **Move Up (0)**.",
        '{"0": -0.5, "1": 1.5, "2": 0, "3": 0}',  # negative -> invalid
        '{"0": NaN, "1": 1, "2": 0, "3": 0}',  # NaN -> invalid
        '{"0": Infinity, "1": 1}',
        '{"0": 0.0, "1": 0.0, "2": 0.0, "3": 0.0, "move to crying baby": 1.0}',  # all zero
        '{"build": 0.0, "distribute": 0.0, "improve": 0.0, "maintain": 0.0}',  # no action key
        'the probabilities of each action are: {"0": 0.5, "1": 0.1, "2": 0.1,',  # cut off
        '{"0": true, "1": false}',
        '{"0": "high", "1": "low"}',
        "{{{{",
        "}}}}{",
    ],
)
def test_abstains_with_uniform(text):
    parsed = parse_belief(text, MILK)
    assert parsed.status == "abstained"
    assert np.allclose(parsed.belief, 0.25)
    assert parsed.error


def test_candidate_spans_order_and_nesting():
    text = 'a {"x": {"y": 1}} b {"z": 2}'
    assert [text[a:b] for a, b in candidate_spans(text)[0]] == [
        '{"z": 2}',
        '{"x": {"y": 1}}',
        '{"y": 1}',
    ]


def test_belief_schema():
    schema = belief_schema(MILK)
    assert list(schema["properties"]) == ["reasoning", "0", "1", "2", "3"]
    assert schema["required"] == ["reasoning", "0", "1", "2", "3"]
    assert schema["properties"]["reasoning"]["maxLength"] == 400
    assert "up" in schema["properties"]["0"]["description"]
    assert list(belief_schema(DRIVE, reasoning=False)["properties"]) == ["0", "1", "2"]


def test_no_actions():
    assert parse_belief("{}", ()).status == "abstained"
