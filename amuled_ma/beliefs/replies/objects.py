"""The ``{...}`` objects of an LLM reply, read with repairs in linear time (limits: below)."""

from __future__ import annotations

import ast
import json
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Longest candidate object examined (longer spans are skipped, keeping parsing fast).
MAX_OBJECT_CHARS = 20_000
#: How many candidate objects (from the end of the text) are examined at most.
MAX_CANDIDATES = 50
#: Characters examined over all candidates: this many times the reply's length, plus
#: `MAX_OBJECT_CHARS` (so nested objects in a short reply are never cut short).
EXAMINE_FACTOR = 4
#: Characters per reply read by ``ast.literal_eval`` (the Python-literal repair); each
#: reading counts at least 50.
MAX_LITERAL_CHARS = 1_000
#: Deepest ``{``/``[`` nesting of a candidate; deeper ones are refused unread.
MAX_NESTING = 32
#: Keys looked at per reply: each object's keys (its nested objects' included) and each
#: colon the lenient ``key: number`` scan looks at. An object with more is not a belief.
MAX_KEYS = 256


class UnreadableObjectError(ValueError):
    """A candidate object cannot be read or cannot be a belief (never escapes the parser)."""


def _codes(text: str) -> np.ndarray:
    """One byte per character (``?`` for those outside Latin-1), for vectorised scans."""
    return np.frombuffer(text.encode("latin-1", "replace"), dtype=np.uint8)


def _depths(steps: np.ndarray) -> np.ndarray:
    """Nesting depth after each step (+1 open, -1 close); a close at depth 0 is ignored."""
    raw = np.cumsum(steps, dtype=np.int32)
    return raw - np.minimum.accumulate(np.minimum(raw, 0))


def candidate_spans(text: str) -> tuple[list[tuple[int, int]], int]:
    """``(start, end)`` of the balanced ``{...}`` spans, the one ending last first.

    Nested ones included, braces in strings too: the first `MAX_CANDIDATES` of at most
    `MAX_OBJECT_CHARS` characters, and how many longer spans were left out.
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


def too_deep(text: str) -> bool:
    """Whether ``{``/``[`` nest deeper than `MAX_NESTING` (brackets in strings count)."""
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


def _run_length(text: str) -> int:
    """Length of the run of key characters that ``text`` starts with (0 for none)."""
    match = _KEY_RUN.match(text)
    return match.end() if match else 0


_KEY_MAX = 80


def _pair_key(text: str, start: int, colon: int) -> str | None:
    """The key of the leftmost ``key: number`` pair starting in ``text[start:colon]``.

    It ends right before the whitespace preceding the colon: the quoted run of key characters
    there, else that unquoted run (its last 80), else one whitespace character (no newline).
    """
    segment = text[start:colon]
    head = segment.rstrip()
    k = len(head)
    if k and head[-1] in "\"'":
        run = _run_length(head[max(0, k - 2 - _KEY_MAX) : k - 1][::-1])
        if 1 <= run <= _KEY_MAX and k - 2 - run >= 0 and head[k - 2 - run] == head[-1]:
            return head[k - 1 - run : k - 1]
    elif k:
        run = _run_length(head[max(0, k - _KEY_MAX) :][::-1])
        if run:
            return head[k - run :]
    tail = segment[k:]
    skip = len(tail) - len(tail.lstrip("\n"))
    return tail[skip] if skip < len(tail) else None


@dataclass
class ReadBudget:
    """What is left to spend on one reply (see the module's docstring)."""

    chars: int  # characters of candidates to examine
    literal: int = MAX_LITERAL_CHARS  # characters to read with ast.literal_eval
    keys: int = MAX_KEYS  # keys and colons to look at

    def spend_keys(self, count: int) -> None:
        """Spend ``count`` keys, or raise `UnreadableObjectError` (spending none)."""
        if count > self.keys:
            raise UnreadableObjectError(f"more than {MAX_KEYS} keys per reply")
        self.keys -= count


def _lenient_pairs(body: str, budget: ReadBudget) -> dict[str, Any]:
    """Scan ``key: number`` pairs (a key's last wins); `UnreadableObjectError`: keys ran out."""
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


def decode_candidate(candidate: str, budget: ReadBudget) -> tuple[dict[str, Any], tuple[str, ...]]:
    """Decode one ``{...}`` span, repairing the usual faults; linear in its length.

    Strict JSON, a Python literal, the repairs, then the lenient ``key: number`` scan; ``budget``
    is spent in place. ``(object, repairs)``; `UnreadableObjectError` when nothing can be read.
    """
    if too_deep(candidate):
        raise UnreadableObjectError(f"nested deeper than {MAX_NESTING} levels")
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
    raise UnreadableObjectError("no readable object")
