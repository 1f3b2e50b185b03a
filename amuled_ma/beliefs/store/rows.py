"""A belief-store row: the table layout (``docs/store.md``), the row record, every value checked."""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from amuled_ma.beliefs.replies.validate import ANSWER_STATUSES, RULE, check_belief, show_values
from amuled_ma.beliefs.store.keys import (
    canonical_json,
    floats_json,
    jsonable,
    names_json,
    string_json,
)
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult
from amuled_ma.errors import AmuledError

#: Statuses whose rows are served back as cached answers.
CACHEABLE = ANSWER_STATUSES
#: Version of the table layout written into ``meta``.
SCHEMA_VERSION = 1

#: The tables (``CREATE ... IF NOT EXISTS``, so running it again changes nothing).
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS texts (hash TEXT PRIMARY KEY, body TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS beliefs (
    key TEXT PRIMARY KEY,
    source TEXT NOT NULL,
    identity TEXT NOT NULL,
    task TEXT NOT NULL,
    cluster TEXT NOT NULL,
    obs TEXT NOT NULL,
    actions TEXT NOT NULL,
    messages TEXT,
    raw TEXT,
    belief TEXT NOT NULL,
    status TEXT NOT NULL,
    latency_s REAL,
    prompt_tokens INTEGER,
    completion_tokens INTEGER,
    extra TEXT,
    attempts INTEGER NOT NULL DEFAULT 1,
    created_at REAL NOT NULL,
    updated_at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS beliefs_task_cluster ON beliefs (task, cluster);
"""

#: The columns of a ``beliefs`` row, in the order of `encode_row`'s tuples.
COLUMNS = (
    "key, source, identity, task, cluster, obs, actions, messages, raw, belief, status, "
    "latency_s, prompt_tokens, completion_tokens, extra, attempts, created_at, updated_at"
)

#: A ``beliefs`` row as a tuple of column values (`COLUMNS` order).
Row = tuple[Any, ...]


class BeliefStoreError(AmuledError, RuntimeError):
    """The belief store file cannot be opened, or a row read or imported is malformed."""


@dataclass
class StoredBelief:
    """One row of the store as read back (``messages`` ``None``: not read, `get_many`)."""

    key: str
    source: str
    identity: dict[str, Any]
    task: str
    cluster: str
    obs: tuple[float, ...]
    action_names: tuple[str, ...]
    messages: tuple[tuple[str, str], ...] | None
    raw: str | None
    belief: np.ndarray
    status: str
    latency_s: float | None
    prompt_tokens: int | None
    completion_tokens: int | None
    extra: dict[str, Any]
    attempts: int
    created_at: float
    updated_at: float

    def request(self) -> BeliefRequest:
        """Return the request this row answers."""
        return BeliefRequest(
            task=self.task,
            cluster=self.cluster,
            obs=self.obs,
            action_names=self.action_names,
            messages=self.messages or (),
        )


def encode_row(
    key: str,
    identity: str,
    request: BeliefRequest,
    belief: np.ndarray,
    answer: BeliefResult | StoredBelief,
    attempts: int,
    created_at: float,
    updated_at: float,
) -> tuple[Row, dict[str, str]]:
    """One answer as a ``beliefs`` row (`COLUMNS` order) and ``{text_hash: body}`` for ``texts``.

    ``belief`` is ``answer``'s, already checked (`check_belief`); ``identity`` is `identity_json`
    text; the messages are stored as ``[[role, text_hash], ...]``.
    """
    messages_ref, bodies = split_messages(request.messages)
    row = (
        key,
        answer.source,
        identity,
        request.task,
        request.cluster,
        floats_json(request.obs),
        names_json(tuple(request.action_names)),
        messages_ref,
        answer.raw,
        floats_json(belief.tolist()),
        answer.status,
        float(answer.latency_s) if answer.latency_s is not None else None,
        answer.prompt_tokens,
        answer.completion_tokens,
        extra_json(answer.extra),
        attempts,
        created_at,
        updated_at,
    )
    return row, bodies


#: The column names of `COLUMNS`, in order.
COLUMN_NAMES = tuple(name.strip() for name in COLUMNS.split(","))


def unstorable_text(value: object, where: str = "") -> str | None:
    r"""Why ``value`` (text, or JSON-like data holding text) cannot be stored as UTF-8, or None.

    A lone surrogate (a byte read with ``surrogateescape``, a ``\ud800`` JSON escape) cannot;
    the reason reads ``"<where> holds ... at character N"`` (``where``: ``raw``, ``extra.error``).
    """
    stack: list[tuple[Any, str]] = [(value, where)]
    while stack:
        item, name = stack.pop()
        if isinstance(item, str):
            try:
                item.encode("utf-8")
            except UnicodeEncodeError as error:
                bad = item[error.start : error.end].encode("utf-8", "backslashreplace")
                return (
                    f"{name or 'a value'} holds {bad.decode('ascii')} at character "
                    f"{error.start}, which is not valid Unicode text (a lone surrogate: a "
                    "byte that was not UTF-8, or a \\ud800-\\udfff escape)"
                )
        elif isinstance(item, Mapping):
            stack.extend((k, f"{name}.<key>") for k in item)
            stack.extend((v, f"{name}.{k}" if name else str(k)) for k, v in item.items())
        elif isinstance(item, list | tuple):
            stack.extend((v, f"{name}[{i}]") for i, v in enumerate(item))
    return None


def check_storable(row: Row) -> str | None:
    """Why a row from `encode_row` cannot be written as UTF-8 text, or None."""
    for name, value in zip(COLUMN_NAMES, row, strict=False):
        reason = unstorable_text(value, name)
        if reason is not None:
            return reason
    return None


def extra_json(extra: Mapping[str, Any] | None) -> str:
    """Diagnostics as standard JSON (``"{}"`` when empty), what it cannot hold (NaN too) as repr."""
    if not extra:
        return "{}"
    plain = jsonable(extra, finite=True)
    try:
        return canonical_json(plain)
    except (TypeError, ValueError):
        return json.dumps(plain, sort_keys=True, default=repr)


@functools.lru_cache(maxsize=4096)
def _text_hash_cached(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _text_hash(text: str) -> str:
    """SHA-256 of a message body, memoising the long ones (shared prompt blocks)."""
    if len(text) < 256:
        return hashlib.sha256(text.encode("utf-8")).hexdigest()
    return _text_hash_cached(text)


def split_messages(
    messages: Sequence[tuple[str, str]],
) -> tuple[str | None, dict[str, str]]:
    """The ``messages`` column (``[[role, text_hash], ...]``, or None) and ``{hash: body}``."""
    if not messages:
        return None, {}
    refs, bodies = [], {}
    for role, content in messages:
        h = _text_hash(content)
        refs.append(f'[{string_json(role)},"{h}"]')  # == canonical_json([[role, h], ...])
        bodies[h] = content
    return "[" + ",".join(refs) + "]", bodies


def damaged_row(where: str, key: str | None, problem: str) -> BeliefStoreError:
    """The error of a damaged row at ``where`` (``"STORE: row KEY"``), with how to remove it."""
    fix = (
        f"delete the row (SQL: DELETE FROM beliefs WHERE key = '{key}') so the next run asks "
        "again, or rebuild the store from an export"
        if key
        else "rebuild the store from an export"
    )
    return BeliefStoreError(
        f"{where}: {problem}; the row is damaged (edited by hand, or written by another "
        f"program or an older amuled-ma); {fix}"
    )


def why_not_json(error: BaseException) -> str:
    """Why `json.loads` failed, for an error message (deep nesting named in words)."""
    if isinstance(error, RecursionError):
        return "nested deeper than Python's JSON reader can follow"
    return str(error)


def load_column(text: Any, column: str, where: str, key: str | None) -> Any:
    """Parse one JSON column of a stored row; text that is not JSON raises `damaged_row`."""
    try:
        return json.loads(text)
    except (TypeError, ValueError, RecursionError) as error:
        raise damaged_row(
            where,
            key,
            f"column {column!r} is not JSON ({why_not_json(error)}): {show_values(text, 80)}",
        ) from None


def load_extra(text: str | None, where: str, key: str) -> dict[str, Any]:
    """Parse the ``extra`` column (a JSON object, else `damaged_row`); NaN becomes ``"nan"``."""
    if not text or text == "{}":
        return {}
    value = load_column(text, "extra", where, key)
    if not isinstance(value, dict):
        raise damaged_row(
            where, key, f"column 'extra' is not a JSON object: {show_values(text, 80)}"
        )
    # rows of an older amuled-ma may hold NaN/Infinity (this one writes "nan"/"inf" text)
    return jsonable(value, finite=True) if "NaN" in text or "Infinity" in text else value


def load_belief(text: str, n_actions: int, where: str, key: str) -> np.ndarray:
    """Parse and check a stored belief of ``n_actions`` values; else `damaged_row`."""
    values = load_column(text, "belief", where, key)
    belief, reason = check_belief(values, n_actions)
    if belief is None:
        raise damaged_row(where, key, f"belief {show_values(values)} {reason}; {RULE}")
    return belief


def message_refs(row: Sequence[Any], path: str) -> list[tuple[str, str]]:
    """The ``[(role, text_hash), ...]`` of a row's ``messages`` column; else `damaged_row`."""
    key = row[0]
    refs = load_column(row[7], "messages", f"{path}: row {key}", key)
    if not isinstance(refs, list) or not all(
        isinstance(r, list) and len(r) == 2 and all(isinstance(x, str) for x in r) for r in refs
    ):
        raise damaged_row(
            f"{path}: row {key}", key, f"column 'messages' is not [[role, hash], ...]: {row[7]!r}"
        )
    return [(r, h) for r, h in refs]


def decode_row(
    row: Sequence[Any], texts: Mapping[str, str] | None, path: str = "<store>"
) -> StoredBelief:
    """Turn a ``beliefs`` row (`COLUMNS` order) into a `StoredBelief`, checking every column.

    ``texts`` (``{text_hash: body}``) holds the row's messages; ``None`` leaves ``messages``
    unread. A damaged column raises `damaged_row`'s `BeliefStoreError`, naming ``path``.
    """
    column = dict(zip(COLUMN_NAMES, row, strict=True))
    key, obs, actions = column["key"], column["obs"], column["actions"]
    where = f"{path}: row {key}"
    messages: tuple[tuple[str, str], ...] | None = None
    if texts is not None:
        refs = message_refs(row, path) if column["messages"] else []
        missing = [h for _, h in refs if h not in texts]
        if missing:
            raise damaged_row(where, key, f"message text {missing[0]} is not in table 'texts'")
        messages = tuple((r, texts[h]) for r, h in refs)
    obs_values = load_column(obs, "obs", where, key)
    names = load_column(actions, "actions", where, key)
    if not isinstance(names, list) or not names or not all(isinstance(a, str) for a in names):
        raise damaged_row(where, key, f"column 'actions' is not a list of names: {actions!r}")
    if not isinstance(obs_values, list) or not all(
        isinstance(x, int | float) and not isinstance(x, bool) for x in obs_values
    ):
        raise damaged_row(where, key, f"column 'obs' is not a list of numbers: {obs!r}")
    del column["actions"]
    column.update(
        identity=load_column(column["identity"], "identity", where, key),
        obs=tuple(obs_values),
        messages=messages,
        belief=load_belief(column["belief"], len(names), where, key),
        extra=load_extra(column["extra"], where, key),
        attempts=int(column["attempts"]),
        created_at=float(column["created_at"]),
        updated_at=float(column["updated_at"]),
    )
    return StoredBelief(**column, action_names=tuple(names))
