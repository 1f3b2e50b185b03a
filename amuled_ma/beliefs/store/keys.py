"""A store key: the SHA-256 of the canonical JSON of the source identity and the full request."""

from __future__ import annotations

import functools
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from amuled_ma.beliefs.types import BeliefRequest

#: Version of the key recipe hashed by `request_key`.
KEY_VERSION = 1


def canonical_json(value: object) -> str:
    """``value`` as canonical JSON: sorted keys, no spaces, UTF-8; equal data, equal text."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def jsonable(value: object, *, finite: bool = False) -> Any:
    """``value`` with numpy values, tuples and non-string keys (any depth) as plain JSON data.

    ``finite`` writes a non-finite float as its repr (``"nan"``), so standard JSON holds it.
    """
    if isinstance(value, Mapping):
        return {str(k): jsonable(v, finite=finite) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v, finite=finite) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist(), finite=finite)
    if isinstance(value, np.generic):
        value = value.item()
    if finite and isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    return value


def identity_json(identity: Mapping[str, Any]) -> str:
    """The canonical JSON of a source's ``identity()``: the form hashed into keys and stored."""
    return canonical_json(jsonable(identity))


def request_key(identity: Mapping[str, Any] | str, request: BeliefRequest) -> str:
    """The store key of one request to one source, 64 hex characters.

    ``sha256(canonical_json({"identity": identity, "request": {"actions", "cluster",
    "messages": [[role, content], ...], "obs", "task"}, "v": KEY_VERSION}))``; ``identity``
    is the source's ``identity()`` or its `identity_json` text (faster for many requests).
    """
    ident = identity if isinstance(identity, str) else identity_json(identity)
    # the prefix up to the last message is shared by a cluster's requests: hashed once
    messages = request.messages
    head, last = (messages[:-1], messages[-1]) if messages else ((), None)
    digest = _prefix_state(ident, tuple(request.action_names), request.cluster, head).copy()
    last_text = (
        f"[{string_json(last[0])},{json.dumps(last[1], ensure_ascii=False)}]"
        if last is not None
        else ""
    )
    obs = floats_json(request.obs)
    tail = f'{last_text}],"obs":{obs},"task":{string_json(request.task)}}},"v":{KEY_VERSION}}}'
    digest.update(tail.encode("utf-8"))
    return digest.hexdigest()


def floats_json(values: Sequence[float]) -> str:
    """``canonical_json([float(x) for x in values])``, fast for finite floats."""
    floats = [float(x) for x in values]
    if all(math.isfinite(x) for x in floats):
        return "[" + ",".join(map(float.__repr__, floats)) + "]"
    return canonical_json(floats)


@functools.lru_cache(maxsize=16384)
def string_json(text: str) -> str:
    """``text`` as JSON, non-ASCII kept (memoised: prompt blocks and roles repeat)."""
    return json.dumps(text, ensure_ascii=False)


@functools.lru_cache(maxsize=256)
def names_json(names: tuple[str, ...]) -> str:
    """The canonical JSON list of action names (memoised: one list per task)."""
    return canonical_json(list(names))


@functools.lru_cache(maxsize=1024)
def _prefix_state(
    ident: str, actions: tuple[str, ...], cluster: str, head: tuple[tuple[str, str], ...]
) -> Any:
    """SHA-256 state after the key text's prefix, up to (not including) the last message."""
    msgs = "".join(f"[{string_json(role)},{string_json(content)}]," for role, content in head)
    text = (
        f'{{"identity":{ident},"request":{{"actions":{names_json(actions)},'
        f'"cluster":{string_json(cluster)},"messages":[{msgs}'
    )
    return hashlib.sha256(text.encode("utf-8"))
