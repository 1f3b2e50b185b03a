"""An LLM reply turned into a belief, never crashing (``docs/beliefs.md``, "Parsing rules")."""

from __future__ import annotations

import contextlib
import functools
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from amuled_ma.beliefs.replies.objects import (
    EXAMINE_FACTOR,
    MAX_KEYS,
    MAX_OBJECT_CHARS,
    ReadBudget,
    UnreadableObjectError,
    candidate_spans,
    decode_candidate,
    too_deep,
)
from amuled_ma.beliefs.replies.validate import SUM_TOLERANCE, show_values
from amuled_ma.beliefs.replies.validate import uniform_belief as uniform

#: Statuses `parse_belief` returns.
PARSE_STATUSES = ("ok", "repaired", "abstained")

#: Repairs that may be listed in `ParsedBelief.repairs` (their meanings: ``docs/beliefs.md``).
REPAIRS = (
    "schema_ignored",
    "python_literal",
    "unquoted_keys",
    "trailing_comma",
    "lenient_pairs",
    "string_values",
    "percent",
    "key_names",
    "nested",
    "extra_keys",
    "duplicate_keys",
    "missing_actions",
    "renormalised",
    "earlier_object",
)

#: Keys that carry text, not probabilities (ignored without an ``extra_keys`` repair).
TEXT_KEYS = frozenset({"reasoning", "reason", "explanation", "rationale", "thoughts", "analysis"})


@dataclass(frozen=True)
class ParsedBelief:
    """One parsed reply: a valid ``belief``, `PARSE_STATUSES`, `REPAIRS`, why it abstained."""

    belief: np.ndarray
    status: str
    repairs: tuple[str, ...] = ()
    reasoning: str | None = None
    error: str | None = None


def belief_schema(
    action_names: Sequence[str], *, reasoning: bool = True, reasoning_max_chars: int = 400
) -> dict[str, Any]:
    """JSON schema of a reply over ``action_names`` (index = key), with an optional reasoning."""
    properties: dict[str, Any] = {}
    if reasoning:
        properties["reasoning"] = {"type": "string", "maxLength": int(reasoning_max_chars)}
    for i, name in enumerate(action_names):
        properties[str(i)] = {
            "type": "number",
            "minimum": 0,
            "maximum": 1,
            "description": f"probability of action {i} ({name})",
        }
    return {
        "type": "object",
        "properties": properties,
        "required": list(properties),
        "additionalProperties": False,
    }


_NOT_WORD = re.compile(r"[^\w ]")
_DIGITS = re.compile(r"\d+")
_ACTION_NUMBER = re.compile(r"(?:action\s*)?(\d+)\b")
_LETTER = re.compile(r"(?:[Aa]ction\s*)?([A-Za-z])")


def _norm(text: str) -> str:
    text = text.lower().replace("_", " ").replace("-", " ")
    return " ".join(_NOT_WORD.sub(" ", text).split())


@functools.lru_cache(maxsize=64)
def _normed_names(names: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(_norm(name) for name in names)


def _key_index(key: str, names: Sequence[str]) -> tuple[int | None, bool]:
    """Map one key to an action index; the flag says whether it was a name, not an index."""
    n = len(names)
    raw = key.strip().strip("\"'").strip()
    if _DIGITS.fullmatch(raw):
        i = int(raw)
        return (i if i < n else None), False
    k = _norm(raw)
    if not k:
        return None, False
    m = _ACTION_NUMBER.match(k)
    if m and "." not in raw[: m.end() + 1]:
        i = int(m.group(1))
        return (i if i < n else None), True
    normed = _normed_names(tuple(names))
    if k in normed:
        return normed.index(k), True
    words = f" {k} "
    hits = [i for i, name in enumerate(normed) if name and f" {name} " in words]
    if len(hits) == 1:
        return hits[0], True
    return None, False


def _letter_index(key: str, n: int) -> int | None:
    raw = key.strip().strip("\"'").strip()
    m = _LETTER.fullmatch(raw)
    if not m:
        return None
    i = ord(m.group(1).upper()) - ord("A")
    return i if i < n else None


def _value(value: object, repairs: set[str]) -> float:
    if isinstance(value, bool):
        raise UnreadableObjectError(f"boolean probability {value!r}")
    if isinstance(value, int | float):
        number = float(value)
    elif isinstance(value, str):
        text = value.strip()
        percent = text.endswith("%")
        try:
            number = float(text.rstrip("%").strip())
        except ValueError:
            raise UnreadableObjectError(
                f"non-numeric probability {show_values(value, 80)}"
            ) from None
        repairs.add("string_values")
        if percent:
            number /= 100.0
            repairs.add("percent")
    else:
        raise UnreadableObjectError(f"non-numeric probability {show_values(value, 80)}")
    if math.isnan(number) or math.isinf(number):
        raise UnreadableObjectError(f"probability {number!r} is not finite")
    if number < 0:
        raise UnreadableObjectError(f"negative probability {number!r}")
    return number


def belief_from_mapping(
    obj: Mapping[str, Any], action_names: Sequence[str]
) -> tuple[np.ndarray, tuple[str, ...], str | None]:
    """One decoded JSON object as ``(belief, repairs, reasoning)``.

    `UnreadableObjectError`: no action named, an invalid probability, a sum of 0, or more than
    `MAX_KEYS` keys (nested objects' included).
    """
    n = len(action_names)
    if _key_count(obj) > MAX_KEYS:
        raise UnreadableObjectError(f"more than {MAX_KEYS} keys")
    names = tuple(action_names)
    nested = [v for v in obj.values() if isinstance(v, Mapping)]
    repairs: set[str] = set()
    reasoning = None
    for key in TEXT_KEYS:
        if isinstance(obj.get(key), str):
            reasoning = obj[key]
            break
    indices = {key: _key_index(str(key), names) for key in obj}
    direct = any(index is not None for index, _ in indices.values())
    if not direct and nested:
        for inner in reversed(nested):
            if _mapped_keys(inner, action_names):
                belief, inner_repairs, inner_reasoning = belief_from_mapping(inner, action_names)
                return (
                    belief,
                    tuple(sorted({*inner_repairs, "nested"})),
                    reasoning or inner_reasoning,
                )
    values = np.zeros(n)
    seen: set[int] = set()
    for key, value in obj.items():
        index, by_name = indices[key]
        key = str(key)
        if index is None and not direct:
            index, by_name = _letter_index(key, n), True
        if index is None:
            if _norm(key) not in TEXT_KEYS:
                repairs.add("extra_keys")
            continue
        if by_name:
            repairs.add("key_names")
        if index in seen:
            repairs.add("duplicate_keys")
        seen.add(index)
        values[index] = _value(value, repairs)
    if not seen:
        raise UnreadableObjectError(f"no key names one of the {n} actions")
    if len(seen) < n:
        repairs.add("missing_actions")
    total = float(values.sum())
    if not total > 0 or not math.isfinite(total):
        raise UnreadableObjectError("all probabilities are 0")
    if abs(total - 1.0) > SUM_TOLERANCE:
        repairs.add("renormalised")
    return values / total, tuple(sorted(repairs)), reasoning


def _mapped_keys(obj: Mapping[str, Any], action_names: Sequence[str]) -> list[int]:
    return [i for key in obj if (i := _key_index(str(key), action_names)[0]) is not None]


def _key_count(obj: Mapping[str, Any]) -> int:
    """How many keys `belief_from_mapping` looks at: the object's and its nested objects'."""
    if len(obj) > MAX_KEYS:
        return len(obj)
    return len(obj) + sum(len(v) for v in obj.values() if isinstance(v, Mapping))


def parse_belief(
    text: str | None, action_names: Sequence[str], *, structured: bool = False
) -> ParsedBelief:
    """Parse one LLM reply (``structured``: asked with `belief_schema`); never raises."""
    n = len(action_names)
    if n == 0:
        return ParsedBelief(np.zeros(0), "abstained", error="no actions")
    try:
        return _parse(text, action_names, structured)
    except Exception as error:
        return ParsedBelief(uniform(n), "abstained", error=f"parser error: {error!r}")


def _result(belief: np.ndarray, repairs: Sequence[str], reasoning: str | None) -> ParsedBelief:
    repairs = tuple(sorted(set(repairs)))
    return ParsedBelief(belief, "repaired" if repairs else "ok", repairs, reasoning)


def _parse(text: str | None, action_names: Sequence[str], structured: bool) -> ParsedBelief:
    n = len(action_names)
    if not isinstance(text, str) or not text.strip():
        return ParsedBelief(uniform(n), "abstained", error="empty reply")
    extra: list[str] = []
    if structured:
        obj = None
        if not too_deep(text):
            with contextlib.suppress(ValueError, RecursionError):
                obj = json.loads(text)
        if isinstance(obj, dict):
            try:
                belief, repairs, reasoning = belief_from_mapping(obj, action_names)
                return _result(belief, repairs, reasoning)
            except UnreadableObjectError:
                pass
        extra.append("schema_ignored")
    reasons: list[str] = []
    spans, too_long = candidate_spans(text)
    budget = ReadBudget(chars=EXAMINE_FACTOR * len(text) + MAX_OBJECT_CHARS)
    skipped = 0
    for position, (start, end) in enumerate(spans):
        if end - start > budget.chars or not budget.keys:
            skipped += 1
            continue
        budget.chars -= end - start
        try:
            obj, decode_repairs = decode_candidate(text[start:end], budget)
            budget.spend_keys(_key_count(obj))
            belief, repairs, reasoning = belief_from_mapping(obj, action_names)
        except (UnreadableObjectError, ValueError, TypeError, OverflowError) as error:
            reasons.append(str(error))
            continue
        earlier = ("earlier_object",) if position else ()
        return _result(belief, (*extra, *decode_repairs, *repairs, *earlier), reasoning)
    if reasons:
        why = f"no valid object: {reasons[0]}"
    elif skipped:
        why = "no valid object"
    else:
        why = "no JSON object in the reply"
    if skipped:
        why += f" ({skipped} candidates not examined: the reply's budget is spent)"
    if too_long and not spans:
        why += f" ({too_long} objects over {MAX_OBJECT_CHARS} characters not read)"
    return ParsedBelief(uniform(n), "abstained", tuple(extra), error=why)
