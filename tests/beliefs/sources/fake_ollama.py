"""Replies of a fake Ollama server, for the tests that mock its HTTP API with ``httpx``."""

from __future__ import annotations

import json
from typing import Any

import httpx

#: A well-formed belief reply over four actions.
GOOD = json.dumps({"reasoning": "go", "0": 0.7, "1": 0.1, "2": 0.1, "3": 0.1})


def chat_reply(body: dict[str, Any], content: str) -> httpx.Response:
    """``/api/chat``'s answer to the request ``body``: the assistant says ``content``."""
    return httpx.Response(
        200,
        json={
            "model": body["model"],
            "created_at": "2026-01-01T00:00:00Z",
            "message": {"role": "assistant", "content": content},
            "done": True,
            "prompt_eval_count": 11,
            "eval_count": 5,
        },
    )
