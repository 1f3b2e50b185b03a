"""A panel member's stated reason, read from its raw reply (what an expert is shown).

The belief store keeps each member's raw reply (``BeliefResult.raw``), as does a replayed
recording of the authors (``exchanges``, for the states their parser needed a second look
at). The reason is the reply's ``reasoning`` field when the reply is a JSON object with one
(an Ollama member asked with the belief schema), the reply's own words when it is free text
(the authors' replies: "Let us think about this step by step ..."), and nothing when the
reply is only numbers or no reply was kept (a rules member, a recording of beliefs only):
the page then says :data:`~amuled_ma.study.model.NO_REASON`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

from amuled_ma.beliefs.replies.parsing import parse_belief

#: Longest reason kept, in characters (the rest is cut, and the cut is said).
MAX_REASON_CHARS = 3000


def stated_reason(raw: str | None, action_names: Sequence[str]) -> str | None:
    """The reason a member gave in its reply ``raw``; None when it gave none.

    Args:
        raw: The member's raw reply (None: none was kept).
        action_names: The task's actions (to read a JSON reply's keys).

    Returns:
        The ``reasoning`` field of a JSON reply, else the reply's text when it is not
        only a JSON object, cut at :data:`MAX_REASON_CHARS` characters; None otherwise.

    """
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
