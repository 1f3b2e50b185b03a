"""A panel member's stated reason, read from its raw reply (what an expert is shown)."""

from __future__ import annotations

import json
from collections.abc import Sequence

from amuled_ma.beliefs.replies.parsing import parse_belief

#: Longest reason kept, in characters (the rest is cut, and the cut is said).
MAX_REASON_CHARS = 3000


def stated_reason(raw: str | None, action_names: Sequence[str]) -> str | None:
    """A JSON reply's ``reasoning``, or its text if not only JSON, cut at `MAX_REASON_CHARS`."""
    if not isinstance(raw, str) or not raw.strip():
        return None
    parsed = parse_belief(raw, action_names)
    text: str | None = parsed.reasoning if isinstance(parsed.reasoning, str) else None
    if not text:
        try:
            whole = json.loads(raw)
        except (ValueError, RecursionError):
            whole = None
        text = None if isinstance(whole, dict | list | int | float) else raw
    if text is None or not text.strip():
        return None
    text = text.strip()
    if len(text) > MAX_REASON_CHARS:
        text = text[:MAX_REASON_CHARS] + f" [... cut at {MAX_REASON_CHARS} characters]"
    return text
