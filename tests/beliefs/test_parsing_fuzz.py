"""Hypothesis fuzzing: parse_belief never raises and always returns a probability vector."""

from __future__ import annotations

import json

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from amuled_ma.beliefs.parsing import parse_belief

MILK = ("up", "down", "left", "right")
FAST = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def assert_belief(parsed, n=4):
    belief = parsed.belief
    assert belief.shape == (n,)
    assert np.all(np.isfinite(belief))
    assert np.all(belief >= 0)
    assert abs(belief.sum() - 1.0) < 1e-9
    assert parsed.status in ("ok", "repaired", "abstained")


@FAST
@given(st.text())
def test_arbitrary_text(text):
    assert_belief(parse_belief(text, MILK))
    assert_belief(parse_belief(text, MILK, structured=True))


JSONISH = st.text(alphabet="{}[]\"':,.-+eE0123456789 naNIfity updownleftright_\n", max_size=200)


@FAST
@given(JSONISH)
def test_json_like_text(text):
    assert_belief(parse_belief(text, MILK))


VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.text(max_size=10),
    st.booleans(),
    st.none(),
)
KEYS = st.one_of(
    st.sampled_from(["0", "1", "2", "3", "4", "up", "Move Down", "A", "reasoning"]),
    st.text(max_size=8),
)


@FAST
@given(st.dictionaries(KEYS, VALUES, max_size=8), st.text(max_size=50), st.text(max_size=50))
def test_objects_in_text(obj, before, after):
    try:
        body = json.dumps(obj)
    except ValueError:
        return
    assert_belief(parse_belief(before + body + after, MILK))
    assert_belief(parse_belief(body, MILK, structured=True))


@FAST
@given(
    st.lists(st.floats(min_value=0, max_value=1e6), min_size=4, max_size=4).filter(
        lambda v: sum(v) > 1e-300
    )
)
def test_valid_vectors_round_trip(values):
    text = json.dumps({str(i): v for i, v in enumerate(values)})
    parsed = parse_belief(text, MILK, structured=True)
    assert parsed.status in ("ok", "repaired")
    expected = np.asarray(values) / np.sum(values)
    assert np.allclose(parsed.belief, expected)


@FAST
@given(st.integers(min_value=1, max_value=12), st.text(max_size=100))
def test_any_action_count(n, text):
    actions = tuple(f"a{i}" for i in range(n))
    assert_belief(parse_belief(text, actions), n)
