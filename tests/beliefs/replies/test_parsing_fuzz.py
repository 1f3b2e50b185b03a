"""Hypothesis fuzzing: parse_belief never raises and always returns a probability vector."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from amuled_ma.beliefs.replies.parsing import PARSE_STATUSES, parse_belief

MILK = ("up", "down", "left", "right")
FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


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


# --------------------------------------------------------------------------- worst-case time
#
# Adversarial replies of 20,000 characters (the longest object read). Each is timed against
# json.loads of a plain JSON document of the same length, in the same run: the parser must
# stay within 10 times that (plus 5 ms of timer noise). The quadratic parser took 48 s on
# the whitespace reply.

SIZE = 20_000


def fit(head: str, unit: str, tail: str = "", size: int = SIZE) -> str:
    """``head + unit * k + tail``, padded with spaces after the units to exactly ``size``."""
    k = (size - len(head) - len(tail)) // len(unit)
    body = head + unit * k
    return body + " " * (size - len(body) - len(tail)) + tail


ADVERSARIAL = {
    "whitespace": lambda n: fit("{a", " ", "}", n),
    "whitespace_colon": lambda n: fit("{a", " ", ":x}", n),
    "newlines": lambda n: fit("{a", " \n", "}", n),
    "nested_braces": lambda n: fit("", "{", "", n // 2) + fit("", "}", "", n - n // 2),
    "unclosed_braces": lambda n: fit("", "{", "", n),
    "empty_objects": lambda n: fit("", "{}", "", n),
    "commas": lambda n: fit("{", ",", "}", n),
    "colons": lambda n: fit("{", ":", "}", n),
    "colon_numbers": lambda n: fit("{", ":0", "}", n),
    "comma_colon_numbers": lambda n: fit("{", ",:0", "}", n),
    "double_quotes": lambda n: fit("{", '"', "}", n),
    "single_quotes": lambda n: fit("{", "'", "}", n),
    "letters": lambda n: fit("{", "a", "}", n),
    "huge_exponent": lambda n: fit('{"0": 1e', "9", "}", n),
    "long_digits": lambda n: fit('{"0": ', "1", "}", n),
    "deep_lists": lambda n: fit('{"0": ', "[", "}", n),
    "deep_balanced_lists": lambda n: fit('{"0": ', "[", "", n // 2) + fit("", "]", "}", n - n // 2),
    "small_objects": lambda n: fit("", "{'x': 1} ", "", n),
    "small_lenient_objects": lambda n: fit("", "{x: 1 y} ", "", n),
}


def best_time(function, repeats: int = 7, give_up_s: float = 1.0) -> float:
    """Fastest of ``repeats`` calls, in seconds (a call over ``give_up_s`` ends the trial)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        elapsed = time.perf_counter() - start
        best = min(best, elapsed)
        if elapsed > give_up_s:
            break
    return best


def json_time(size: int) -> float:
    """Time of json.loads of a plain JSON list of ``size`` characters."""
    document = fit("[", "0,", "0]", size)
    assert len(document) == size
    assert json.loads(document) == [0] * ((size - 2) // 2)
    return best_time(lambda: json.loads(document))


@pytest.mark.parametrize("shape", sorted(ADVERSARIAL))
def test_worst_case_time_is_within_10x_json(shape):
    text = ADVERSARIAL[shape](SIZE)
    assert len(text) == SIZE
    parsed = parse_belief(text, MILK)
    assert_belief(parsed)
    parse_s = best_time(lambda: parse_belief(text, MILK))
    assert parse_s <= 10 * json_time(SIZE) + 0.005, f"{shape}: {parse_s * 1e3:.1f} ms"


@pytest.mark.parametrize("shape", sorted(ADVERSARIAL))
def test_time_grows_linearly(shape):
    """4 times the length takes well under 16 times (quadratic) the time."""
    quarter = best_time(lambda: parse_belief(ADVERSARIAL[shape](SIZE // 4), MILK))
    full = best_time(lambda: parse_belief(ADVERSARIAL[shape](SIZE), MILK))
    assert full <= 8 * quarter + 0.001, f"{shape}: {quarter * 1e3:.2f} ms -> {full * 1e3:.2f} ms"


def test_long_reply_of_many_objects_is_linear():
    """Past the longest object, the reply's length still costs linear time."""
    unit = '{"0": 0.5, "1": 0.5} junk {"colour": "blue"} '
    short = unit * (SIZE // len(unit))
    long = unit * (4 * SIZE // len(unit))
    assert parse_belief(long, MILK).status == "repaired"  # earlier_object
    quarter = best_time(lambda: parse_belief(short, MILK))
    full = best_time(lambda: parse_belief(long, MILK))
    assert full <= 8 * quarter + 0.001


# --------------------------------------------------------------------------- limits


@pytest.mark.parametrize(
    "text",
    [
        '{"0": ' + "[" * 9_000 + "]" * 9_000 + "}",
        "{" * 9_000 + "}" * 9_000,
        '{"0": 1, "x": ' + "[" * 40 + "]" * 40 + "}",
    ],
)
@pytest.mark.parametrize("structured", [False, True])
def test_deep_nesting_abstains_with_a_reason(text, structured):
    parsed = parse_belief(text, MILK, structured=structured)
    assert parsed.status == "abstained"
    assert np.allclose(parsed.belief, 0.25)
    assert "nested deeper" in parsed.error


@pytest.mark.parametrize("structured", [False, True])
def test_nesting_past_the_recursion_limit_never_raises(structured):
    for text in ("[" * 200_000, "{" * 200_000 + "}" * 200_000, '{"0": ' + "[" * 200_000 + "}"):
        assert_belief(parse_belief(text, MILK, structured=structured))


def test_shallow_nesting_is_read():
    text = '{"x": ' + "[" * 10 + "]" * 10 + ', "0": 1}'
    parsed = parse_belief(text, MILK, structured=True)
    assert np.allclose(parsed.belief, [1, 0, 0, 0])


def test_brackets_in_strings_cannot_smuggle_deep_nesting():
    """Closing brackets in strings hide the depth from the pre-check; json still copes."""
    deep = '["]]]]]]]]",' * 3_000 + "]" * 3_000
    for text in ('{"x": ' + deep + ', "0": 1}', '{"0": 1, "x": ' + deep + "}"):
        for structured in (False, True):
            assert_belief(parse_belief(text, MILK, structured=structured))


def test_an_object_with_hundreds_of_keys_is_not_a_belief():
    keys = {f"note {i}": 0 for i in range(300)}
    parsed = parse_belief(json.dumps({"0": 1, **keys}), MILK)
    assert parsed.status == "abstained"
    assert "keys" in parsed.error
    parsed = parse_belief(json.dumps({"0": 1, **dict(list(keys.items())[:20])}), MILK)
    assert np.allclose(parsed.belief, [1, 0, 0, 0])


def test_nested_objects_in_a_short_reply_are_all_examined():
    """The examination budget never cuts short a reply of a few nested objects."""
    text = '{"a": {"b": {"c": {"d": {"e": {"0": 1}}}}}}'
    parsed = parse_belief(text, MILK)
    assert np.allclose(parsed.belief, [1, 0, 0, 0])
    assert "earlier_object" in parsed.repairs


def test_many_large_nested_candidates_are_skipped_with_a_reason():
    text = '{"x": ' * 20 + "[" + "0, " * 6_000 + "0]" + "}" * 20
    parsed = parse_belief(text, MILK)
    assert parsed.status == "abstained"
    assert "not examined" in parsed.error


# --------------------------------------------------------------------------- adversarial fuzz

BLOCKS = st.sampled_from(
    [
        " ",
        "\n",
        "\t",
        "{",
        "}",
        "[",
        "]",
        "(",
        ")",
        '"',
        "'",
        ":",
        ",",
        "0",
        "1",
        "0.5",
        "1e999",
        "-",
        "%",
        "nan",
        "up",
        "Move Up",
        "action 2",
        "A",
        "reasoning",
        '"0": 0.5',
        "'1': 0.5",
        "3: 0.25",
        "{'0': 1}",
        '{"1": 1}',
        "True",
        "None",
        "\\",
        "\u00a0",
        "é",
    ]
)
ADVERSARIAL_TEXT = st.lists(
    st.tuples(BLOCKS, st.integers(min_value=1, max_value=400)), max_size=12
).map(lambda runs: "".join(block * count for block, count in runs))


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(ADVERSARIAL_TEXT, st.integers(min_value=1, max_value=8), st.booleans())
def test_adversarial_replies_always_give_a_belief(text, n, structured):
    actions = MILK if n == 4 else tuple(f"a{i}" for i in range(n))
    parsed = parse_belief(text, actions, structured=structured)
    assert parsed.status in PARSE_STATUSES
    assert parsed.belief.dtype == np.float64
    assert_belief(parsed, n)
    assert (parsed.status == "abstained") == (parsed.error is not None)
