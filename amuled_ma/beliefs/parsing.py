"""Turn an LLM reply into a belief vector, and never crash doing it.

The order of attempts (documented in ``docs/beliefs.md``):

1. **Structured reply** (``structured=True``, the Ollama ``format`` schema of
   :func:`belief_schema`): the whole reply is one JSON object with one probability per
   action key (``"0"``, ``"1"``, ...) and optionally ``"reasoning"``.
2. **Last JSON object in the text**: every balanced ``{...}`` span is a candidate, the
   one ending last is tried first, then earlier ones; the first candidate that yields a
   valid belief wins. Each candidate is read with strict JSON, then with repairs
   (Python literal syntax / single quotes, unquoted keys, trailing commas, and finally a
   lenient ``key: number`` scan).
3. **Abstain**: a uniform belief with status ``"abstained"`` and the reason in
   :attr:`ParsedBelief.error`.

A candidate object is turned into a belief by :func:`belief_from_mapping`: keys may be
action indices (``"0"``), ``"action 0"``, action names (``"up"``, ``"Move Up"``,
``"move_up"``) or letters (``"A"``); keys that name no action are ignored; missing
actions get 0; a negative, NaN, infinite or non-numeric probability makes the whole
object invalid; a sum other than 1 is renormalised; an all-zero object is invalid.

An unclosed object (a reply cut off by the token limit) is not completed: the missing
probabilities are unknown, not zero, so such a reply abstains, as the authors' parser did.
"""

from __future__ import annotations

import ast
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Statuses :func:`parse_belief` returns.
PARSE_STATUSES = ("ok", "repaired", "abstained")

#: Repairs that may be listed in :attr:`ParsedBelief.repairs`.
REPAIRS = {
    "schema_ignored": "structured output was requested but the reply is not the schema's JSON",
    "python_literal": "object read as a Python literal (single quotes, True/None, ...)",
    "unquoted_keys": "keys or string values were not quoted; quotes added",
    "trailing_comma": "a trailing comma before '}' was removed",
    "lenient_pairs": "object read by scanning 'key: number' pairs",
    "string_values": "probabilities given as strings were converted to numbers",
    "percent": "probabilities given as percentages were divided by 100",
    "key_names": "keys named actions ('up', 'Move Up', 'action 0', 'A') instead of indices",
    "nested": "probabilities were found in a nested object",
    "extra_keys": "keys that name no action were ignored",
    "duplicate_keys": "several keys named the same action; the last one was kept",
    "missing_actions": "actions missing from the object were given probability 0",
    "renormalised": "probabilities did not sum to 1 and were renormalised",
    "earlier_object": "the last JSON object was invalid; an earlier one was used",
}

#: Keys that carry text, not probabilities (ignored without an ``extra_keys`` repair).
TEXT_KEYS = frozenset({"reasoning", "reason", "explanation", "rationale", "thoughts", "analysis"})

#: Absolute tolerance on the sum of probabilities before it counts as a repair.
SUM_TOLERANCE = 1e-6
#: Longest candidate object examined (longer spans are skipped, keeping parsing fast).
MAX_OBJECT_CHARS = 20_000
#: How many candidate objects (from the end of the text) are examined at most.
MAX_CANDIDATES = 50


@dataclass(frozen=True)
class ParsedBelief:
    """The result of parsing one reply.

    Attributes:
        belief: Probability vector, shape ``(n_actions,)``: finite, >= 0, sums to 1.
        status: ``"ok"`` (read as is), ``"repaired"`` (see ``repairs``) or
            ``"abstained"`` (uniform; nothing usable in the reply).
        repairs: Names of the repairs applied, keys of :data:`REPAIRS`.
        reasoning: The reply's ``"reasoning"`` field, when there was one.
        error: Why the reply abstained (``None`` otherwise).

    """

    belief: np.ndarray
    status: str
    repairs: tuple[str, ...] = ()
    reasoning: str | None = None
    error: str | None = None


class InvalidBeliefError(ValueError):
    """A candidate object cannot be a belief (internal to parsing; never escapes)."""


def uniform(n_actions: int) -> np.ndarray:
    """Return the uniform belief over ``n_actions`` actions."""
    return np.full(n_actions, 1.0 / n_actions)


def belief_schema(
    action_names: Sequence[str], *, reasoning: bool = True, reasoning_max_chars: int = 400
) -> dict[str, Any]:
    """JSON schema of a structured reply, for Ollama's ``format`` argument.

    Args:
        action_names: The task's action names; index = action id = property key.
        reasoning: Put a short ``"reasoning"`` string before the probabilities.
        reasoning_max_chars: Maximum length of the reasoning string.

    Returns:
        ``{"type": "object", "properties": {"reasoning": ..., "0": ..., ...}, ...}``.

    """
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


# --------------------------------------------------------------------------- keys


def _norm(text: str) -> str:
    text = text.lower().replace("_", " ").replace("-", " ")
    return " ".join(re.sub(r"[^\w ]", " ", text).split())


def _key_index(key: str, names: Sequence[str]) -> tuple[int | None, bool]:
    """Map one key to an action index; the flag says whether it was a name, not an index."""
    n = len(names)
    raw = key.strip().strip("\"'").strip()
    if re.fullmatch(r"\d+", raw):
        i = int(raw)
        return (i if i < n else None), False
    k = _norm(raw)
    if not k:
        return None, False
    m = re.match(r"(?:action\s*)?(\d+)\b", k)
    if m and "." not in raw[: m.end() + 1]:
        i = int(m.group(1))
        return (i if i < n else None), True
    normed = [_norm(name) for name in names]
    if k in normed:
        return normed.index(k), True
    words = f" {k} "
    hits = [i for i, name in enumerate(normed) if name and f" {name} " in words]
    if len(hits) == 1:
        return hits[0], True
    return None, False


def _letter_index(key: str, n: int) -> int | None:
    raw = key.strip().strip("\"'").strip()
    m = re.fullmatch(r"(?:[Aa]ction\s*)?([A-Za-z])", raw)
    if not m:
        return None
    i = ord(m.group(1).upper()) - ord("A")
    return i if i < n else None


# --------------------------------------------------------------------------- values


def _value(value: Any, repairs: set[str]) -> float:
    if isinstance(value, bool):
        raise InvalidBeliefError(f"boolean probability {value!r}")
    if isinstance(value, int | float):
        number = float(value)
    elif isinstance(value, str):
        text = value.strip()
        percent = text.endswith("%")
        try:
            number = float(text.rstrip("%").strip())
        except ValueError:
            raise InvalidBeliefError(f"non-numeric probability {value!r}") from None
        repairs.add("string_values")
        if percent:
            number /= 100.0
            repairs.add("percent")
    else:
        raise InvalidBeliefError(f"non-numeric probability {value!r}")
    if math.isnan(number) or math.isinf(number):
        raise InvalidBeliefError(f"probability {number!r} is not finite")
    if number < 0:
        raise InvalidBeliefError(f"negative probability {number!r}")
    return number


def belief_from_mapping(
    obj: Mapping[str, Any], action_names: Sequence[str]
) -> tuple[np.ndarray, tuple[str, ...], str | None]:
    """Turn one decoded object into a belief.

    Args:
        obj: The decoded JSON object.
        action_names: The task's action names.

    Returns:
        ``(belief, repairs, reasoning)``.

    Raises:
        InvalidBeliefError: The object names no action, holds an invalid probability, or
            sums to 0.

    """
    n = len(action_names)
    repairs: set[str] = set()
    reasoning = None
    for key in TEXT_KEYS:
        if isinstance(obj.get(key), str):
            reasoning = obj[key]
            break
    nested = [v for v in obj.values() if isinstance(v, Mapping)]
    direct = _mapped_keys(obj, action_names)
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
        key = str(key)
        index, by_name = _key_index(key, action_names)
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
        raise InvalidBeliefError(f"no key names one of the {n} actions")
    if len(seen) < n:
        repairs.add("missing_actions")
    total = float(values.sum())
    if not total > 0 or not math.isfinite(total):
        raise InvalidBeliefError("all probabilities are 0")
    if abs(total - 1.0) > SUM_TOLERANCE:
        repairs.add("renormalised")
    return values / total, tuple(sorted(repairs)), reasoning


def _mapped_keys(obj: Mapping[str, Any], action_names: Sequence[str]) -> list[int]:
    return [i for key in obj if (i := _key_index(str(key), action_names)[0]) is not None]


# --------------------------------------------------------------------------- objects


def candidate_objects(text: str) -> list[str]:
    """Every balanced ``{...}`` span of the text, the one ending last first.

    Nested spans are all returned (an outer object ends after its inner ones, so it
    comes first). Braces inside quoted strings are not special-cased: replies rarely
    hold them, and a failed outer candidate falls back to the inner ones.
    """
    spans: list[tuple[int, int]] = []
    stack: list[int] = []
    for i, ch in enumerate(text):
        if ch == "{":
            stack.append(i)
        elif ch == "}" and stack:
            start = stack.pop()
            if i + 1 - start <= MAX_OBJECT_CHARS:
                spans.append((start, i + 1))
    spans.sort(key=lambda s: (s[1], -s[0]), reverse=True)
    return [text[a:b] for a, b in spans[:MAX_CANDIDATES]]


_UNQUOTED_KEY = re.compile(r"([{,]\s*)([A-Za-z0-9_][A-Za-z0-9_ \-]*?)\s*:")
_SINGLE_QUOTED = re.compile(r"'([^'\"]*)'")
_TRAILING_COMMA = re.compile(r",\s*([}\]])")
_PAIR = re.compile(
    r"""(["']?)([^"'{},:\n]{1,80}?)\1\s*:\s*(["']?)"""
    r"""(-?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?%?|-?nan|-?inf(?:inity)?)\3""",
    re.IGNORECASE,
)


def decode_object(candidate: str) -> tuple[dict[str, Any], tuple[str, ...]]:
    """Decode one ``{...}`` span, repairing the usual faults.

    Returns:
        ``(object, repairs)``.

    Raises:
        InvalidBeliefError: Nothing could be read.

    """
    try:
        obj = json.loads(candidate)
        if isinstance(obj, dict):
            return obj, ()
    except (ValueError, RecursionError):
        pass
    try:
        obj = ast.literal_eval(candidate)
        if isinstance(obj, dict):
            return {str(k): v for k, v in obj.items()}, ("python_literal",)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        pass
    repairs = []
    fixed = candidate
    step = _SINGLE_QUOTED.sub(r'"\1"', fixed)
    step = _UNQUOTED_KEY.sub(r'\1"\2":', step)
    if step != fixed:
        repairs.append("unquoted_keys")
        fixed = step
    step = _TRAILING_COMMA.sub(r"\1", fixed)
    if step != fixed:
        repairs.append("trailing_comma")
        fixed = step
    try:
        obj = json.loads(fixed)
        if isinstance(obj, dict):
            return obj, tuple(repairs)
    except (ValueError, RecursionError):
        pass
    pairs: dict[str, Any] = {}
    for match in _PAIR.finditer(candidate[1:-1]):
        pairs[match.group(2).strip()] = match.group(4)
    if pairs:
        return pairs, ("lenient_pairs",)
    raise InvalidBeliefError("no readable object")


# --------------------------------------------------------------------------- entry


def parse_belief(
    text: str | None, action_names: Sequence[str], *, structured: bool = False
) -> ParsedBelief:
    """Parse one LLM reply into a belief over the task's actions; never raises.

    Args:
        text: The raw reply (``None`` or empty abstains).
        action_names: The task's action names; index = action id.
        structured: The reply was requested with :func:`belief_schema` as format.

    Returns:
        The parsed belief with its status and repairs.

    """
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
        try:
            obj = json.loads(text)
        except (ValueError, RecursionError):
            obj = None
        if isinstance(obj, dict):
            try:
                belief, repairs, reasoning = belief_from_mapping(obj, action_names)
                return _result(belief, repairs, reasoning)
            except InvalidBeliefError:
                pass
        extra.append("schema_ignored")
    reasons: list[str] = []
    for position, candidate in enumerate(candidate_objects(text)):
        try:
            obj, decode_repairs = decode_object(candidate)
            belief, repairs, reasoning = belief_from_mapping(obj, action_names)
        except (InvalidBeliefError, ValueError, TypeError, OverflowError) as error:
            reasons.append(str(error))
            continue
        earlier = ("earlier_object",) if position else ()
        return _result(belief, (*extra, *decode_repairs, *repairs, *earlier), reasoning)
    error = "no JSON object in the reply" if not reasons else f"no valid object: {reasons[0]}"
    return ParsedBelief(uniform(n), "abstained", tuple(extra), error=error)
