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

**Cost: linear in the reply's length**, whatever the reply. The braces are matched in one
vectorised pass; at most :data:`MAX_CANDIDATES` candidates of at most
:data:`MAX_OBJECT_CHARS` characters are examined, all of them together at most
``EXAMINE_FACTOR * len(reply) + MAX_OBJECT_CHARS`` characters (a candidate that does not
fit in what is left is skipped). Each step on a candidate is linear: ``json``; regular
expressions that never backtrack over a run of characters; a ``key: number`` scan that
visits each colon once. Per reply, ``ast.literal_eval`` (about 50 times slower per
character than ``json``) reads at most :data:`MAX_LITERAL_CHARS` characters, and at most
:data:`MAX_KEYS` keys are looked at. A candidate nested deeper than :data:`MAX_NESTING`
levels of ``{``/``[`` is refused unread, and no ``RecursionError`` escapes. A reply that
trips a limit abstains like any other reply without a usable object, the limit named in
:attr:`ParsedBelief.error`.
"""

from __future__ import annotations

import ast
import contextlib
import functools
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
#: Characters examined over all candidates: this many times the reply's length, plus
#: :data:`MAX_OBJECT_CHARS` (so nested objects in a short reply are never cut short).
EXAMINE_FACTOR = 4
#: Characters per reply read by ``ast.literal_eval`` (the Python-literal repair); each
#: reading counts at least 50.
MAX_LITERAL_CHARS = 1_000
#: Deepest ``{``/``[`` nesting of a candidate; deeper ones are refused unread.
MAX_NESTING = 32
#: Keys looked at per reply: each object's keys (its nested objects' included) and each
#: colon the lenient ``key: number`` scan looks at. An object with more is not a belief.
MAX_KEYS = 256


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


# --------------------------------------------------------------------------- values


def _brief(value: Any) -> str:
    """``repr(value)``, at most 80 characters (an error message never holds a whole reply)."""
    try:
        text = repr(value)
    except RecursionError:  # a value nested deeper than the stack allows
        text = f"<deeply nested {type(value).__name__}>"
    return text if len(text) <= 80 else f"{text[:77]}..."


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
            raise InvalidBeliefError(f"non-numeric probability {_brief(value)}") from None
        repairs.add("string_values")
        if percent:
            number /= 100.0
            repairs.add("percent")
    else:
        raise InvalidBeliefError(f"non-numeric probability {_brief(value)}")
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
        InvalidBeliefError: The object names no action, holds an invalid probability,
            sums to 0, or has more than :data:`MAX_KEYS` keys (nested objects' included).

    """
    n = len(action_names)
    if _key_count(obj) > MAX_KEYS:
        raise InvalidBeliefError(f"more than {MAX_KEYS} keys")
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


def _key_count(obj: Mapping[str, Any]) -> int:
    """How many keys :func:`belief_from_mapping` looks at: the object's and its nested objects'."""
    if len(obj) > MAX_KEYS:
        return len(obj)
    return len(obj) + sum(len(v) for v in obj.values() if isinstance(v, Mapping))


# --------------------------------------------------------------------------- objects


def _codes(text: str) -> np.ndarray:
    """One byte per character (``?`` for those outside Latin-1), for vectorised scans."""
    return np.frombuffer(text.encode("latin-1", "replace"), dtype=np.uint8)


def _depths(steps: np.ndarray) -> np.ndarray:
    """Nesting depth after each step (+1 open, -1 close); a close at depth 0 is ignored."""
    raw = np.cumsum(steps, dtype=np.int32)
    return raw - np.minimum.accumulate(np.minimum(raw, 0))


def _candidate_spans(text: str) -> tuple[list[tuple[int, int]], int]:
    """``(start, end)`` of the balanced ``{...}`` spans, the one ending last first.

    Returns:
        The first :data:`MAX_CANDIDATES` spans of at most :data:`MAX_OBJECT_CHARS`
        characters, and how many longer spans were left out.

    """
    if "{" not in text or "}" not in text:
        return [], 0
    codes = _codes(text)
    where = np.flatnonzero((codes == ord("{")) | (codes == ord("}")))
    opens = codes[where] == ord("{")
    after = _depths(np.where(opens, 1, -1))
    before = np.concatenate(([0], after[:-1]))
    # An open brace sits at the level it opens, a matched close brace at the level it
    # closes; per level, sorted by position, they alternate open, close, open, close...
    level = np.where(opens, after, before)
    events = np.flatnonzero(opens | (before > 0))
    keys = level[events]
    if keys.size and keys.max() < 2**16:
        keys = keys.astype(np.uint16)  # a stable sort of 16-bit keys is a linear radix sort
    events = events[np.argsort(keys, kind="stable")]
    paired = opens[events[:-1]] & ~opens[events[1:]]
    paired &= level[events[:-1]] == level[events[1:]]
    start = np.full(where.size, -1)  # per close brace: where its object starts, or -1
    start[events[1:][paired]] = where[events[:-1][paired]]
    closed = start >= 0
    short = closed & (where + 1 - start <= MAX_OBJECT_CHARS)
    last = np.flatnonzero(short)[::-1][:MAX_CANDIDATES]
    spans = list(zip(start[last].tolist(), (where[last] + 1).tolist(), strict=True))
    return spans, int(np.count_nonzero(closed & ~short))


def candidate_objects(text: str) -> list[str]:
    """Every balanced ``{...}`` span of the text, the one ending last first.

    Nested spans are all returned (an outer object ends after its inner ones, so it
    comes first). Braces inside quoted strings are not special-cased: replies rarely
    hold them, and a failed outer candidate falls back to the inner ones. At most
    :data:`MAX_CANDIDATES` spans of at most :data:`MAX_OBJECT_CHARS` characters are
    returned; the cost is linear in the text's length.
    """
    return [text[a:b] for a, b in _candidate_spans(text)[0]]


def _too_deep(text: str) -> bool:
    """Whether ``{``/``[`` nest deeper than :data:`MAX_NESTING` (brackets in strings count)."""
    if text.count("{") + text.count("[") <= MAX_NESTING:
        return False
    codes = _codes(text)
    opens = (codes == ord("{")) | (codes == ord("["))
    closes = (codes == ord("}")) | (codes == ord("]"))
    steps = opens.astype(np.int8) - closes.astype(np.int8)
    return int(_depths(steps).max()) > MAX_NESTING


# The repairs' patterns match each run of characters once: possessive quantifiers
# (``*+``) never give back what they took, so no pattern backtracks over a run.
# A key's inner spaces are taken only when a key character follows them.
_UNQUOTED_KEY = re.compile(
    r"([{,]\s*+)([A-Za-z0-9_](?:[A-Za-z0-9_\-]| ++(?=[A-Za-z0-9_\-]))*+)\s*+:"
)
_SINGLE_QUOTED = re.compile(r"'([^'\"]*+)'")
_TRAILING_COMMA = re.compile(r",\s*+([}\]])")
# The lenient scan reads ``key: number`` pairs: a key of 1 to 80 characters (none of
# ``"'{},:`` or a newline), optionally quoted, then a colon, then a number, optionally
# quoted. It starts at each colon followed by a number (_VALUE) and looks back for the key.
# (The lookahead only rejects most colons faster.)
_VALUE = re.compile(
    r""":(?=\s*+["']?[-.\dni])\s*+(["']?)"""
    r"""(-?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?%?|-?nan|-?inf(?:inity)?)\1""",
    re.IGNORECASE,
)
_KEY_RUN = re.compile(r"[^\"'{},:\n]*")
_KEY_MAX = 80


def _pair_key(text: str, start: int, colon: int) -> str | None:
    """The key of the leftmost ``key: number`` pair starting in ``text[start:colon]``.

    The pair's key ends right before the whitespace preceding the colon: it is the
    quoted run of key characters there, else that unquoted run (its last 80
    characters), else one whitespace character (other than a newline) of that
    whitespace; ``None`` if there is none of these.
    """
    segment = text[start:colon]
    head = segment.rstrip()
    k = len(head)
    if k and head[-1] in "\"'":
        run = _KEY_RUN.match(head[max(0, k - 2 - _KEY_MAX) : k - 1][::-1]).end()
        if 1 <= run <= _KEY_MAX and k - 2 - run >= 0 and head[k - 2 - run] == head[-1]:
            return head[k - 1 - run : k - 1]
    elif k:
        run = _KEY_RUN.match(head[max(0, k - _KEY_MAX) :][::-1]).end()
        if run:
            return head[k - run :]
    tail = segment[k:]
    skip = len(tail) - len(tail.lstrip("\n"))
    return tail[skip] if skip < len(tail) else None


@dataclass
class _Budget:
    """What is left to spend on one reply (see the module's docstring)."""

    chars: int  # characters of candidates to examine
    literal: int = MAX_LITERAL_CHARS  # characters to read with ast.literal_eval
    keys: int = MAX_KEYS  # keys and colons to look at

    def spend_keys(self, count: int) -> None:
        """Spend ``count`` keys, or raise :class:`InvalidBeliefError` (spending none)."""
        if count > self.keys:
            raise InvalidBeliefError(f"more than {MAX_KEYS} keys per reply")
        self.keys -= count


def _lenient_pairs(body: str, budget: _Budget) -> dict[str, Any]:
    """Scan ``key: number`` pairs (the last one of a key wins); linear in ``len(body)``.

    Raises:
        InvalidBeliefError: The budget's keys ran out (one per colon followed by a number).

    """
    pairs: dict[str, Any] = {}
    end = 0
    for value in _VALUE.finditer(body):
        budget.spend_keys(1)
        colon = value.start()
        key = _pair_key(body, max(end, body.rfind(":", 0, colon) + 1), colon)
        if key is not None:
            pairs[key.strip()] = value.group(2)
            end = value.end()
    return pairs


def _decode(candidate: str, budget: _Budget) -> tuple[dict[str, Any], tuple[str, ...]]:
    if _too_deep(candidate):
        raise InvalidBeliefError(f"nested deeper than {MAX_NESTING} levels")
    try:
        obj = json.loads(candidate)
        if isinstance(obj, dict):
            return obj, ()
    except (ValueError, RecursionError):
        pass
    literal_cost = max(len(candidate), 50)
    if literal_cost <= budget.literal:
        budget.literal -= literal_cost
        try:
            obj = ast.literal_eval(candidate)
            if isinstance(obj, dict):
                return {str(k): v for k, v in obj.items()}, ("python_literal",)
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            pass
    repairs = []
    fixed = candidate
    # re.sub(pattern, template) calls Python code for each match; split + join does not.
    step = '"'.join(_SINGLE_QUOTED.split(fixed)) if "'" in fixed else fixed  # 'a' -> "a"
    if ":" in step:
        parts = _UNQUOTED_KEY.split(step)  # [before, "{ ", key, before, ", ", key, ..., after]
        parts[2::3] = [f'"{key}":' for key in parts[2::3]]
        step = "".join(parts)
    if step != fixed:
        repairs.append("unquoted_keys")
        fixed = step
    step = "".join(_TRAILING_COMMA.split(fixed)) if "," in fixed else fixed  # ", }" -> "}"
    if step != fixed:
        repairs.append("trailing_comma")
        fixed = step
    try:
        obj = json.loads(fixed)
        if isinstance(obj, dict):
            return obj, tuple(repairs)
    except (ValueError, RecursionError):
        pass
    pairs = _lenient_pairs(candidate[1:-1], budget)
    if pairs:
        return pairs, ("lenient_pairs",)
    raise InvalidBeliefError("no readable object")


def decode_object(candidate: str) -> tuple[dict[str, Any], tuple[str, ...]]:
    """Decode one ``{...}`` span, repairing the usual faults; linear in its length.

    A span of more than :data:`MAX_LITERAL_CHARS` characters is not read as a Python
    literal (:func:`parse_belief` counts that limit over a whole reply).

    Returns:
        ``(object, repairs)``.

    Raises:
        InvalidBeliefError: Nothing could be read, the span is nested deeper than
            :data:`MAX_NESTING` levels, or the lenient scan would look at more than
            :data:`MAX_KEYS` colons.

    """
    return _decode(candidate, _Budget(chars=len(candidate)))


# --------------------------------------------------------------------------- entry


def parse_belief(
    text: str | None, action_names: Sequence[str], *, structured: bool = False
) -> ParsedBelief:
    """Parse one LLM reply into a belief over the task's actions; never raises.

    The cost is linear in ``len(text)`` (see the module's docstring for the limits).

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
        obj = None
        if not _too_deep(text):
            with contextlib.suppress(ValueError, RecursionError):
                obj = json.loads(text)
        if isinstance(obj, dict):
            try:
                belief, repairs, reasoning = belief_from_mapping(obj, action_names)
                return _result(belief, repairs, reasoning)
            except InvalidBeliefError:
                pass
        extra.append("schema_ignored")
    reasons: list[str] = []
    spans, too_long = _candidate_spans(text)
    budget = _Budget(chars=EXAMINE_FACTOR * len(text) + MAX_OBJECT_CHARS)
    skipped = 0
    for position, (start, end) in enumerate(spans):
        if end - start > budget.chars or not budget.keys:
            skipped += 1
            continue
        budget.chars -= end - start
        try:
            obj, decode_repairs = _decode(text[start:end], budget)
            budget.spend_keys(_key_count(obj))
            belief, repairs, reasoning = belief_from_mapping(obj, action_names)
        except (InvalidBeliefError, ValueError, TypeError, OverflowError) as error:
            reasons.append(str(error))
            continue
        earlier = ("earlier_object",) if position else ()
        return _result(belief, (*extra, *decode_repairs, *repairs, *earlier), reasoning)
    if reasons:
        error = f"no valid object: {reasons[0]}"
    elif skipped:
        error = "no valid object"
    else:
        error = "no JSON object in the reply"
    if skipped:
        error += f" ({skipped} candidates not examined: the reply's budget is spent)"
    if too_long and not spans:
        error += f" ({too_long} objects over {MAX_OBJECT_CHARS} characters not read)"
    return ParsedBelief(uniform(n), "abstained", tuple(extra), error=error)
