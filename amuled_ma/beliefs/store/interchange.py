"""JSON Lines export and import of the belief store (``amuled beliefs export`` / ``import``)."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Sequence
from typing import IO, Any

from amuled_ma.beliefs.replies.validate import RULE, check_belief, show_values
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.keys import identity_json, jsonable, request_key
from amuled_ma.beliefs.store.rows import (
    BeliefStoreError,
    StoredBelief,
    damaged_row,
    unstorable_text,
    why_not_json,
)
from amuled_ma.beliefs.types import STATUSES, BeliefRequest
from amuled_ma.files.limits import read_line

#: Longest line read by `import_jsonl` [characters, 16 Mi]; a row with its chat is about
#: 20,000; a longer line is refused before it is read whole.
MAX_LINE_CHARS = 2**24

_REQUIRED = ("key", "source", "identity", "task", "cluster", "obs", "actions", "belief")


def row_json(row: StoredBelief) -> dict[str, Any]:
    """A row read with its chat (`iter_rows`) as one JSON object, one line of the export."""
    out = {
        "actions" if f.name == "action_names" else f.name: jsonable(getattr(row, f.name))
        for f in dataclasses.fields(row)
    }
    out["messages"] = out["messages"] or []
    return out


def export_jsonl(
    store: BeliefStore,
    fp: IO[str],
    *,
    status: Sequence[str] | None = None,
    task: str | None = None,
) -> int:
    """Write a store's rows of ``status`` and ``task`` (all when None) as JSON Lines; the count.

    `BeliefStoreError`: a damaged row, or a value standard JSON cannot hold.
    """
    count = 0
    for row in store.iter_rows(status=status, task=task):
        try:
            line = json.dumps(row_json(row), ensure_ascii=False, allow_nan=False)
        except ValueError as error:  # a NaN/inf in a column other than the belief
            raise damaged_row(
                f"{store.path}: row {row.key}", row.key, f"not standard JSON ({error})"
            ) from error
        fp.write(line + "\n")
        count += 1
    return count


def import_jsonl(
    store: BeliefStore,
    fp: IO[str],
    *,
    name: str = "<jsonl>",
    verify: bool = True,
    batch: int = 500,
) -> dict[str, int]:
    """Read rows written by `export_jsonl` into a store; an existing answer is never replaced.

    ``name`` names the file in errors; ``verify`` recomputes each key from its row; ``batch``
    rows go in one transaction (the batches before a bad line are kept). Returns ``{"read": n,
    "written": m}``. `BeliefStoreError` names the file and line of one that is not a valid row.
    """
    read = written = 0
    rows: list[StoredBelief] = []
    lineno = 0
    while True:
        where = f"{name}:{lineno + 1}"
        try:
            line = read_line(
                fp,
                MAX_LINE_CHARS,
                where,
                error=BeliefStoreError,
                fix="each line is one row written by 'amuled beliefs export'; is it the right "
                "file?",
            )
        except UnicodeDecodeError as error:
            raise BeliefStoreError(
                f"{where}: not UTF-8 text ({error}); export files are UTF-8"
            ) from None
        if not line:
            break
        lineno += 1
        if not line.strip():
            continue
        rows.append(parse_line(line, f"{name}:{lineno}", verify))
        read += 1
        if len(rows) >= batch:
            written += store.put_rows(rows)
            rows = []
    written += store.put_rows(rows)
    return {"read": read, "written": written}


def _finite_number(value: object) -> bool:
    """True for an int or float (not a bool) that is a finite float64."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def _reject_constant(name: str) -> Any:
    """``parse_constant`` of the JSONL reader: ``NaN``, ``Infinity`` are not standard JSON."""
    raise ValueError(f"{name} is not standard JSON (JSON has no NaN or infinity)")


def parse_line(line: str, where: str, verify: bool = True) -> StoredBelief:
    """One exported line as a row (``verify``: as `import_jsonl`); else `BeliefStoreError`."""
    try:
        obj = json.loads(line, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as error:
        raise BeliefStoreError(
            f"{where}: not JSON ({why_not_json(error)}); each line must be one standard JSON "
            "object written by 'amuled beliefs export' (fix or remove the line)"
        ) from None
    if not isinstance(obj, dict):
        raise BeliefStoreError(
            f"{where}: expected a JSON object (one exported row), found {show_values(obj, 80)}"
        )
    missing = [k for k in (*_REQUIRED, "status") if k not in obj]
    if missing:
        raise BeliefStoreError(f"{where}: missing field(s) {', '.join(missing)}")
    unstorable = unstorable_text(obj)
    if unstorable is not None:
        raise BeliefStoreError(
            f"{where}: {unstorable}; a store holds UTF-8 text only (fix or remove the line)"
        )
    for field in ("key", "source", "task", "cluster", "status"):
        if not isinstance(obj[field], str) or not obj[field]:
            raise BeliefStoreError(
                f"{where}: {field} must be a non-empty string, found {show_values(obj[field], 80)}"
            )
    for field, kinds in (("raw", str), ("prompt_tokens", int), ("completion_tokens", int)):
        value = obj.get(field)
        if value is not None and (isinstance(value, bool) or not isinstance(value, kinds)):
            raise BeliefStoreError(
                f"{where}: {field} must be a {kinds.__name__} or null, found "
                f"{show_values(value, 80)}"
            )
    if obj["status"] not in STATUSES:
        raise BeliefStoreError(f"{where}: status {obj['status']!r} is not one of {STATUSES}")
    key = obj["key"]
    at = f"{where} (key {key})"
    actions = obj["actions"]
    if not isinstance(actions, list) or not actions or not all(isinstance(a, str) for a in actions):
        raise BeliefStoreError(f"{at}: actions must be a list of names, found {actions!r}")
    belief, reason = check_belief(obj["belief"], len(actions))
    if belief is None:
        raise BeliefStoreError(
            f"{at}: belief {show_values(obj['belief'])} {reason}; {RULE} ({len(actions)} "
            "actions); fix or remove the line and import the file again (rows already "
            "imported are kept, never duplicated)"
        )
    obs = obj["obs"]
    if not isinstance(obs, list) or not all(_finite_number(x) for x in obs):
        raise BeliefStoreError(f"{at}: obs must be a list of finite numbers, found {obs!r}")
    try:
        messages = tuple((str(r), str(c)) for r, c in obj.get("messages") or [])
    except (TypeError, ValueError) as error:
        raise BeliefStoreError(f"{at}: messages must be [[role, text], ...] ({error})") from None
    request = BeliefRequest(
        task=obj["task"],
        cluster=obj["cluster"],
        obs=tuple(float(x) for x in obs),
        action_names=tuple(actions),
        messages=messages,
    )
    if verify:
        expected = request_key(identity_json(obj["identity"]), request)
        if expected != key:
            raise BeliefStoreError(
                f"{where}: key {key[:12]}... does not match the row's content "
                f"(expected {expected[:12]}...); the row was edited or written by another "
                "key version (import with --no-verify to keep it anyway)"
            )
    extra = obj.get("extra") or {}
    if not isinstance(extra, dict):
        raise BeliefStoreError(f"{at}: extra must be a JSON object, found {show_values(extra, 80)}")
    latency = obj.get("latency_s")
    now = time.time()
    try:
        return StoredBelief(
            key=key,
            source=obj["source"],
            identity=jsonable(obj["identity"]),
            task=request.task,
            cluster=request.cluster,
            obs=request.obs,
            action_names=request.action_names,
            messages=messages,
            raw=obj.get("raw"),
            belief=belief,
            status=obj["status"],
            latency_s=None if latency is None else float(latency),
            prompt_tokens=obj.get("prompt_tokens"),
            completion_tokens=obj.get("completion_tokens"),
            extra=extra,
            attempts=int(obj.get("attempts") or 1),
            created_at=float(obj.get("created_at") or now),
            updated_at=float(obj.get("updated_at") or now),
        )
    except (TypeError, ValueError) as error:
        raise BeliefStoreError(f"{at}: malformed row ({error})") from None
