"""Persistent belief store: one SQLite row per belief request ever answered.

LLM calls are the slowest and most fragile part of a run, so every answer is kept on
disk and a re-run never sends the same request twice. The store is a plain SQLite file
(standard library only) in WAL mode with a busy timeout, so several processes (parallel
seeds, a sweep) may read and write it at once, and a process killed in the middle of a
write (``kill -9``, an OOM kill, a pulled plug on a GPU box job) leaves every committed
row intact and the file consistent.

## Key

A row is keyed by :func:`request_key`: the SHA-256 (hex) of the canonical JSON (sorted
keys, no spaces, UTF-8) of::

    {"v": 1,
     "identity": source.identity(),        # source kind, model name + digest, options,
                                           # output schema / format, seed, num_ctx, ...
     "task": request.task, "cluster": request.cluster,
     "obs": [float, ...], "actions": [name, ...],
     "messages": [[role, content], ...]}   # the full chat, system prompt and few-shot included

Anything that can change an answer is in the key; two sources with the same identity share
rows, two different ones never do.

## Schema (version 1)

``beliefs``: ``key`` (primary key), ``source``, ``identity`` (canonical JSON), ``task``,
``cluster``, ``obs`` / ``actions`` (JSON lists), ``messages`` (JSON ``[[role, text_hash],
...]``: each message's content lives once in ``texts``, so the system prompt and few-shot
examples shared by every row are stored once), ``raw`` (the raw reply), ``belief`` (JSON list),
``status`` (:data:`~amuled_ma.beliefs.types.STATUSES`), ``latency_s``, ``prompt_tokens``,
``completion_tokens``, ``extra`` (JSON), ``attempts``, ``created_at`` / ``updated_at`` (Unix
seconds). ``texts``: ``hash`` (SHA-256 of the content) -> ``body``. ``meta``: ``schema_version``.

## What is served back

Only rows with status ``"ok"`` or ``"repaired"`` (:data:`CACHEABLE`) are answers; they are
never overwritten. Rows with any other status (``"abstained"``, ``"timeout"``, ``"error"``,
...) are kept for the record (the raw reply of an abstention is evidence of a model's
failure) but are *not* served as cache hits, so the next run asks again; a later
``ok``/``repaired`` answer replaces them and ``attempts`` counts the tries.

## Every belief is checked

Every row's ``belief`` is a valid belief of its row's action count
(:mod:`amuled_ma.beliefs.validate`: finite, non-negative, one value per action, summing
to 1 within 1e-6), whatever its status: an answer holds the model's belief, any other row
the fallback the run used. :meth:`BeliefStore.put_many` refuses to write anything else
(:class:`BeliefStoreError` naming the key and what was found; the
:class:`~amuled_ma.beliefs.cached.CachedSource` in front of it has already turned an
invalid answer into status ``"error"``), and every read refuses a row whose columns are
not JSON or whose belief is invalid (a file edited by hand, or written by an older
amuled-ma), naming the store, the key and how to remove the row. Export writes standard
JSON only; import refuses ``NaN``/``Infinity``, JSON nested deeper than Python can read,
and invalid beliefs, naming the file and line.

## Read-only use

``BeliefStore(path, read_only=True)`` (``amuled beliefs stats`` and ``export``) opens an
existing file with SQLite's ``mode=ro``, creating nothing, and writes nothing. Where even
that cannot work (WAL mode needs a ``-shm`` file beside the store, which cannot be created
in a folder you may not write), it opens the file ``immutable=1``: a snapshot of what was
checkpointed into the main file, without the changes still in a ``-wal`` file.

## Durability

Every write is one short ``BEGIN IMMEDIATE`` transaction. ``synchronous=NORMAL`` (the WAL
default) makes a committed transaction survive a crash of the *process*; pass
``synchronous="FULL"`` to also survive a power loss at some write speed.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import sqlite3
import threading
import time
import urllib.parse
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from amuled_ma.beliefs.types import STATUSES, BeliefRequest, BeliefResult
from amuled_ma.beliefs.validate import RULE, check_belief, show_values
from amuled_ma.errors import AmuledError

#: Statuses whose rows are served back as cached answers.
CACHEABLE = frozenset({"ok", "repaired"})
#: Version of the table layout written into ``meta``.
SCHEMA_VERSION = 1
#: Version of the key recipe hashed by :func:`request_key`.
KEY_VERSION = 1
#: Environment variable naming the default store file.
STORE_ENV = "AMULED_BELIEF_STORE"

_SQL_CHUNK = 500  # keys per ``IN (...)`` query, well under SQLite's variable limit

_SCHEMA = """
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

_COLUMNS = (
    "key, source, identity, task, cluster, obs, actions, messages, raw, belief, status, "
    "latency_s, prompt_tokens, completion_tokens, extra, attempts, created_at, updated_at"
)

# Insert, or replace a row that holds no answer yet; an ok/repaired row is never replaced.
_UPSERT = f"""
INSERT INTO beliefs ({_COLUMNS}) VALUES ({", ".join("?" * 18)})
ON CONFLICT (key) DO UPDATE SET
    raw = excluded.raw, belief = excluded.belief, status = excluded.status,
    latency_s = excluded.latency_s, prompt_tokens = excluded.prompt_tokens,
    completion_tokens = excluded.completion_tokens, extra = excluded.extra,
    attempts = beliefs.attempts + excluded.attempts, updated_at = excluded.updated_at
WHERE beliefs.status NOT IN ('ok', 'repaired')
"""


class BeliefStoreError(AmuledError, RuntimeError):
    """The belief store file cannot be opened, or an imported row is malformed."""


def default_store_path() -> Path:
    """Where the store lives when none is named.

    Returns:
        ``$AMULED_BELIEF_STORE`` if set, else ``$XDG_CACHE_HOME/amuled/beliefs.sqlite``
        (``~/.cache/amuled/beliefs.sqlite``).

    """
    env = os.environ.get(STORE_ENV)
    if env:
        return Path(env)
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "amuled" / "beliefs.sqlite"


def canonical_json(value: Any) -> str:
    """Serialise ``value`` as canonical JSON: sorted keys, no spaces, UTF-8 text.

    Args:
        value: JSON-compatible data (dicts, lists, str, int, float, bool, None).

    Returns:
        The JSON text; equal data always gives the same text.

    """
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def identity_json(identity: Mapping[str, Any]) -> str:
    """Canonical JSON of a source's :meth:`~amuled_ma.beliefs.types.BeliefSource.identity`."""
    return canonical_json(_jsonable(identity))


def request_key(identity: Mapping[str, Any] | str, request: BeliefRequest) -> str:
    """Return the store key of one request to one source (see the module docstring).

    Args:
        identity: The source's ``identity()`` dict, or its :func:`identity_json` text
            (faster when hashing many requests to one source).
        request: The request.

    Returns:
        64 hex characters.

    """
    ident = identity if isinstance(identity, str) else identity_json(identity)
    # Byte for byte canonical_json({"identity": ..., "request": {...}, "v": KEY_VERSION}),
    # hashed in two parts: the prefix up to the last message (identity, actions, cluster,
    # system prompt, few-shot turns: shared by every request of one cluster) is hashed once
    # per process and its SHA-256 state copied; only the state prompt and obs are new.
    messages = request.messages
    head, last = (messages[:-1], messages[-1]) if messages else ((), None)
    digest = _prefix_state(ident, tuple(request.action_names), request.cluster, head).copy()
    last_text = (
        f"[{_enc(last[0])},{json.dumps(last[1], ensure_ascii=False)}]" if last is not None else ""
    )
    obs = _floats_json(request.obs)
    tail = f'{last_text}],"obs":{obs},"task":{_enc(request.task)}}},"v":{KEY_VERSION}}}'
    digest.update(tail.encode("utf-8"))
    return digest.hexdigest()


def _floats_json(values: Sequence[float]) -> str:
    """Return ``canonical_json([float(x) for x in values])``, fast for finite floats."""
    floats = [float(x) for x in values]
    if all(math.isfinite(x) for x in floats):
        return "[" + ",".join(map(float.__repr__, floats)) + "]"
    return canonical_json(floats)


@functools.lru_cache(maxsize=1024)
def _prefix_state(
    ident: str, actions: tuple[str, ...], cluster: str, head: tuple[tuple[str, str], ...]
) -> Any:
    """SHA-256 state after the key text's prefix, up to (not including) the last message."""
    msgs = "".join(f"[{_enc(role)},{_enc(content)}]," for role, content in head)
    text = (
        f'{{"identity":{ident},"request":{{"actions":{_enc_names(actions)},'
        f'"cluster":{_enc(cluster)},"messages":[{msgs}'
    )
    return hashlib.sha256(text.encode("utf-8"))


@functools.lru_cache(maxsize=16384)
def _enc(text: str) -> str:
    """JSON-encode a string (memoised: prompt blocks and roles repeat across requests)."""
    return json.dumps(text, ensure_ascii=False)


@functools.lru_cache(maxsize=256)
def _enc_names(names: tuple[str, ...]) -> str:
    return canonical_json(list(names))


def _extra_json(extra: Mapping[str, Any] | None) -> str:
    """Serialise diagnostics as standard JSON.

    Anything JSON cannot hold is written as its repr (an exception...), and so is a
    non-finite float (``"nan"``, ``"inf"``), so no row ever holds a non-standard ``NaN``.
    """
    if not extra:
        return "{}"
    plain = _plain(extra)
    try:
        return canonical_json(plain)
    except (TypeError, ValueError):
        return json.dumps(plain, sort_keys=True, default=repr)


def _plain(value: Any) -> Any:
    """:func:`_jsonable`, with non-finite floats written as their repr (``"nan"``)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    return value


def _jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and tuples into plain JSON data."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


@dataclass
class StoredBelief:
    """One row of the store, as read back.

    Attributes:
        key: The row's key.
        source: Source name.
        identity: The source identity (parsed JSON).
        task: Task name.
        cluster: Cluster name.
        obs: The observation.
        action_names: Action names.
        messages: The chat, ``((role, content), ...)``; ``None`` when not read (see
            :meth:`BeliefStore.get_many`).
        raw: The raw reply.
        belief: The belief vector (float64).
        status: Answer status.
        latency_s: Seconds the original request took.
        prompt_tokens: Prompt tokens, if reported.
        completion_tokens: Completion tokens, if reported.
        extra: Free-form diagnostics.
        attempts: How many answers were written for this key.
        created_at: Unix time of the first write.
        updated_at: Unix time of the last write.

    """

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

    @property
    def cacheable(self) -> bool:
        """True when the row is an answer served back as a cache hit."""
        return self.status in CACHEABLE

    def to_result(self) -> BeliefResult:
        """Return the row as a cache-hit :class:`BeliefResult` (``cached=True``, latency 0)."""
        extra = dict(self.extra)
        extra["stored_latency_s"] = self.latency_s
        return BeliefResult(
            belief=self.belief.copy(),
            status=self.status,
            source=self.source,
            raw=self.raw,
            cached=True,
            latency_s=0.0,
            prompt_tokens=self.prompt_tokens,
            completion_tokens=self.completion_tokens,
            extra=extra,
        )

    def to_json(self) -> dict[str, Any]:
        """Return the row as one JSON object (the export format, one line per row)."""
        return {
            "key": self.key,
            "source": self.source,
            "identity": self.identity,
            "task": self.task,
            "cluster": self.cluster,
            "obs": list(self.obs),
            "actions": list(self.action_names),
            "messages": [list(m) for m in self.messages or ()],
            "raw": self.raw,
            "belief": self.belief.tolist(),
            "status": self.status,
            "latency_s": self.latency_s,
            "prompt_tokens": self.prompt_tokens,
            "completion_tokens": self.completion_tokens,
            "extra": self.extra,
            "attempts": self.attempts,
            "created_at": self.created_at,
            "updated_at": self.updated_at,
        }

    def request(self) -> BeliefRequest:
        """Return the request this row answers."""
        return BeliefRequest(
            task=self.task,
            cluster=self.cluster,
            obs=self.obs,
            action_names=self.action_names,
            messages=self.messages or (),
        )


class BeliefStore:
    """A SQLite file of belief answers, shared safely by threads and processes.

    Args:
        path: The database file (created with its folder when missing); ``":memory:"``
            for a private in-memory store (tests).
        timeout_s: How long a writer waits for another process's lock before failing.
        synchronous: SQLite ``synchronous`` level, ``"NORMAL"`` (crash-safe for the
            process) or ``"FULL"`` (also power-loss safe).
        read_only: Open an existing file for reading only (SQLite ``mode=ro``, else
            ``immutable=1`` where ``mode=ro`` cannot open it; see the module doc):
            nothing is created or written, and every write raises.

    Raises:
        BeliefStoreError: The file cannot be opened or is not a belief store.

    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        timeout_s: float = 60.0,
        synchronous: str = "NORMAL",
        read_only: bool = False,
    ) -> None:
        self.path = str(path)
        self.timeout_s = float(timeout_s)
        if synchronous.upper() not in {"OFF", "NORMAL", "FULL", "EXTRA"}:
            raise BeliefStoreError(f"synchronous must be NORMAL or FULL, got {synchronous!r}")
        self.synchronous = synchronous.upper()
        self.read_only = bool(read_only)
        #: How the file is open: ``"read-write"``, ``"read-only"`` or ``"immutable"``.
        self.open_mode = "read-only" if self.read_only else "read-write"
        self._lock = threading.RLock()
        self._conn: sqlite3.Connection | None = None
        self._pid = -1
        self._messages_seen: set[str] = set()
        self._text_cache: dict[str, str] = {}
        self._width: dict[str, int] = {}  # ``actions`` column text -> action count
        self._connect()

    # -- connection ------------------------------------------------------------------
    def _connect(self) -> sqlite3.Connection:
        """Open (or, after a ``fork``, re-open) this process's connection."""
        if self._conn is not None and self._pid == os.getpid():
            return self._conn
        if self.read_only:
            return self._connect_read_only()
        if self.path != ":memory:":
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        try:
            conn = sqlite3.connect(
                self.path, timeout=self.timeout_s, isolation_level=None, check_same_thread=False
            )
            conn.execute(f"PRAGMA busy_timeout = {int(self.timeout_s * 1000)}")
            if self.path != ":memory:":
                mode = self._journal_wal(conn)
                if str(mode).lower() != "wal":
                    raise BeliefStoreError(f"{self.path}: cannot switch to WAL mode (got {mode})")
            conn.execute(f"PRAGMA synchronous = {self.synchronous}")
            self._conn, self._pid = conn, os.getpid()
            self._messages_seen = set()
            self._write(lambda c: self._create_schema(c))
        except sqlite3.DatabaseError as error:
            self._conn = None
            raise BeliefStoreError(f"{self.path}: cannot open belief store: {error}") from error
        return conn

    def _journal_wal(self, conn: sqlite3.Connection) -> str:
        """Switch to WAL mode, waiting up to ``timeout_s`` for other processes' locks.

        SQLite does not call the busy handler for this switch, so several processes
        creating one new store at once (parallel seeds) would otherwise fail at once
        with "database is locked".
        """
        deadline = time.monotonic() + self.timeout_s
        while True:
            try:
                return str(conn.execute("PRAGMA journal_mode = WAL").fetchone()[0])
            except sqlite3.OperationalError as error:
                if "locked" not in str(error) or time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def _connect_read_only(self) -> sqlite3.Connection:
        """Open an existing file with ``mode=ro``, else ``immutable=1``; create nothing."""
        path = Path(self.path)
        if self.path == ":memory:" or not path.is_file():
            raise BeliefStoreError(
                f"no belief store at {self.path} to open read-only (give --store PATH or set "
                f"{STORE_ENV})"
            )
        quoted = urllib.parse.quote(str(path.resolve()))
        failures = []
        for mode in ("mode=ro", "immutable=1"):
            conn = None
            try:
                conn = sqlite3.connect(
                    f"file:{quoted}?{mode}",
                    uri=True,
                    timeout=self.timeout_s,
                    isolation_level=None,
                    check_same_thread=False,
                )
                conn.execute(f"PRAGMA busy_timeout = {int(self.timeout_s * 1000)}")
                self._check_schema(conn)
            except sqlite3.DatabaseError as error:
                if conn is not None:
                    conn.close()
                failures.append(f"{mode}: {error}")
                if "not a database" in str(error) or "no such table" in str(error):
                    break  # the file itself is wrong: immutable=1 cannot help
                continue
            self._conn, self._pid = conn, os.getpid()
            self.open_mode = "read-only" if mode == "mode=ro" else "immutable"
            return conn
        raise BeliefStoreError(
            f"{self.path}: cannot open belief store read-only ({'; '.join(failures)}); "
            "check that the file is a belief store and readable"
        )

    @staticmethod
    def _check_schema(conn: sqlite3.Connection) -> None:
        row = conn.execute("SELECT value FROM meta WHERE name = 'schema_version'").fetchone()
        if row is None or int(row[0]) != SCHEMA_VERSION:
            found = "none" if row is None else row[0]
            raise BeliefStoreError(
                f"belief store schema version {found}, this amuled-ma reads {SCHEMA_VERSION}"
            )

    @staticmethod
    def _create_schema(conn: sqlite3.Connection) -> None:
        for statement in _SCHEMA.split(";"):
            if statement.strip():
                conn.execute(statement)
        row = conn.execute("SELECT value FROM meta WHERE name = 'schema_version'").fetchone()
        if row is None:
            conn.execute(
                "INSERT INTO meta (name, value) VALUES ('schema_version', ?)",
                (str(SCHEMA_VERSION),),
            )
        elif int(row[0]) != SCHEMA_VERSION:
            raise BeliefStoreError(
                f"belief store schema version {row[0]}, this amuled-ma reads {SCHEMA_VERSION}"
            )

    def _write(self, body: Any) -> Any:
        """Run ``body(conn)`` in one ``BEGIN IMMEDIATE`` transaction."""
        if self.read_only:
            raise BeliefStoreError(
                f"{self.path}: the belief store is open read-only; open it without "
                "read_only=True (and with write access to the file and its folder) to write"
            )
        with self._lock:
            conn = self._conn if self._pid == os.getpid() else self._connect()
            assert conn is not None
            conn.execute("BEGIN IMMEDIATE")
            try:
                out = body(conn)
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")
            return out

    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            try:
                return self._connect().execute(sql, params).fetchall()
            except sqlite3.DatabaseError as error:
                raise BeliefStoreError(
                    f"{self.path}: cannot read the belief store: {error}; if the file is "
                    "damaged, restore it from an export ('amuled beliefs import') or delete "
                    "it (every belief is then asked again)"
                ) from error

    def close(self) -> None:
        """Close this process's connection (the file stays)."""
        with self._lock:
            if self._conn is not None and self._pid == os.getpid():
                self._conn.close()
            self._conn = None

    def __enter__(self) -> BeliefStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- reads -----------------------------------------------------------------------
    def get_many(
        self, keys: Iterable[str], *, cacheable_only: bool = True, with_messages: bool = False
    ) -> dict[str, StoredBelief]:
        """Read the rows of ``keys`` that exist.

        Args:
            keys: Keys to look up (duplicates allowed).
            cacheable_only: Return only rows served as answers (``ok``/``repaired``).
            with_messages: Also read each row's chat (slower; ``messages`` is ``None``
                otherwise).

        Returns:
            ``{key: row}`` for the keys found.

        """
        wanted = list(dict.fromkeys(keys))
        found: dict[str, StoredBelief] = {}
        status_filter = " AND status IN ('ok', 'repaired')" if cacheable_only else ""
        for start in range(0, len(wanted), _SQL_CHUNK):
            chunk = wanted[start : start + _SQL_CHUNK]
            sql = (
                f"SELECT {_COLUMNS} FROM beliefs "
                f"WHERE key IN ({','.join('?' * len(chunk))}){status_filter}"
            )
            rows = self._read(sql, chunk)
            texts = self._texts(rows) if with_messages else None
            for row in rows:
                stored = _row_to_stored(row, texts, self.path)
                found[stored.key] = stored
        return found

    def _texts(self, rows: Sequence[Sequence[Any]]) -> dict[str, str]:
        """Fetch the message bodies referenced by ``rows``."""
        hashes = {h for row in rows if row[7] for _, h in _messages_refs(row, self.path)}
        texts: dict[str, str] = {}
        todo = [h for h in hashes if h not in self._text_cache]
        for start in range(0, len(todo), _SQL_CHUNK):
            chunk = todo[start : start + _SQL_CHUNK]
            sql = f"SELECT hash, body FROM texts WHERE hash IN ({','.join('?' * len(chunk))})"
            texts.update(self._read(sql, chunk))
        for h in hashes:
            if h in self._text_cache:
                texts[h] = self._text_cache[h]
        if len(self._text_cache) > 4096:
            self._text_cache.clear()
        # keep the bodies shared by many rows (system prompt, few-shot turns) at hand
        for h, body in texts.items():
            if len(body) > 2000:
                self._text_cache[h] = body
        return texts

    def lookup(self, keys: Iterable[str]) -> dict[str, BeliefResult]:
        """Read the answers (``ok``/``repaired`` rows) of ``keys`` as cache-hit results.

        The fast path of :class:`~amuled_ma.beliefs.cached.CachedSource`: only the columns
        of a :class:`BeliefResult` are read and parsed.

        Args:
            keys: Keys to look up (duplicates allowed).

        Returns:
            ``{key: result}`` (``cached=True``, ``latency_s=0``, the original latency in
            ``extra["stored_latency_s"]``) for the keys found.

        """
        wanted = list(dict.fromkeys(keys))
        found: dict[str, BeliefResult] = {}
        width = self._width
        for start in range(0, len(wanted), _SQL_CHUNK):
            chunk = wanted[start : start + _SQL_CHUNK]
            sql = (
                "SELECT key, source, raw, belief, status, latency_s, prompt_tokens, "
                "completion_tokens, extra, actions FROM beliefs "
                f"WHERE key IN ({','.join('?' * len(chunk))}) AND status IN ('ok', 'repaired')"
            )
            for key, source, raw, belief, status, lat, ptok, ctok, extra, actions in self._read(
                sql, chunk
            ):
                where = f"{self.path}: row {key}"
                n = width.get(actions)
                if n is None:
                    names = _load_column(actions, "actions", where, key)
                    if not isinstance(names, list) or not names:
                        raise _bad_row(where, key, f"actions is not a list of names: {actions!r}")
                    n = width[actions] = len(names)
                info = _load_extra(extra, where, key)
                info["stored_latency_s"] = lat
                found[key] = BeliefResult(
                    belief=_stored_belief(belief, n, where, key),
                    status=status,
                    source=source,
                    raw=raw,
                    cached=True,
                    latency_s=0.0,
                    prompt_tokens=ptok,
                    completion_tokens=ctok,
                    extra=info,
                )
        return found

    def get(
        self, key: str, *, cacheable_only: bool = True, with_messages: bool = True
    ) -> StoredBelief | None:
        """Read one row, chat included by default, or ``None`` (see :meth:`get_many`)."""
        rows = self.get_many([key], cacheable_only=cacheable_only, with_messages=with_messages)
        return rows.get(key)

    def iter_rows(
        self, *, status: Sequence[str] | None = None, task: str | None = None
    ) -> Iterator[StoredBelief]:
        """Iterate over every row, oldest first (the export order).

        Args:
            status: Only these statuses (all when ``None``).
            task: Only this task (all when ``None``).

        Yields:
            The rows.

        """
        where, params = [], []
        if status:
            where.append(f"status IN ({','.join('?' * len(status))})")
            params.extend(status)
        if task:
            where.append("task = ?")
            params.append(task)
        sql = (
            f"SELECT {_COLUMNS} FROM beliefs"
            + (f" WHERE {' AND '.join(where)}" if where else "")
            + " ORDER BY created_at, rowid"
        )
        rows = self._read(sql, params)
        for start in range(0, len(rows), _SQL_CHUNK):
            chunk = rows[start : start + _SQL_CHUNK]
            texts = self._texts(chunk)
            for row in chunk:
                yield _row_to_stored(row, texts, self.path)

    def identities(self) -> list[dict[str, Any]]:
        """Return each distinct source identity in the store with its row count.

        Returns:
            ``[{"identity": {...}, "rows": n, "answers": m}, ...]``, most rows first; pass
            an ``identity`` to :class:`~amuled_ma.beliefs.cached.CachedSource` to replay the
            store without the source's backend.

        """
        rows = self._read(
            "SELECT identity, COUNT(*), SUM(status IN ('ok', 'repaired')) FROM beliefs "
            "GROUP BY identity ORDER BY 2 DESC"
        )
        out = []
        for ident, n, m in rows:
            where = f"{self.path}: identity {ident[:60]!r}"
            identity = _load_column(ident, "identity", where, None)
            out.append({"identity": identity, "rows": n, "answers": int(m or 0)})
        return out

    def __len__(self) -> int:
        return int(self._read("SELECT COUNT(*) FROM beliefs")[0][0])

    def __contains__(self, key: object) -> bool:
        return bool(self._read("SELECT 1 FROM beliefs WHERE key = ?", (key,)))

    # -- writes ----------------------------------------------------------------------
    def put_many(
        self, items: Iterable[tuple[str, Mapping[str, Any] | str, BeliefRequest, BeliefResult]]
    ) -> int:
        """Write answers in one transaction.

        An existing ``ok``/``repaired`` row is kept as it is; any other existing row is
        replaced and its ``attempts`` counted up.

        Every belief, whatever its status, must be valid for the request's action count
        (:mod:`amuled_ma.beliefs.validate`); it is written divided by its sum.

        Args:
            items: ``(key, identity, request, result)`` tuples; ``identity`` is the
                source's ``identity()`` dict or its :func:`identity_json` text.

        Returns:
            The number of rows inserted or replaced.

        Raises:
            BeliefStoreError: A belief is invalid (nothing of the batch is written).

        """
        now = time.time()
        rows, texts = [], {}
        for key, identity, request, result in items:
            belief, reason = check_belief(result.belief, len(request.action_names))
            if belief is None:
                raise BeliefStoreError(
                    f"{self.path}: refusing to write row {key} ({request.task} / "
                    f"{request.cluster}, status {result.status!r}, source {result.source!r}): "
                    f"belief {show_values(result.belief)} {reason}; {RULE}; pass a source's "
                    "answers through CachedSource (or amuled_ma.beliefs.validate."
                    "checked_result), which turns an invalid answer into status 'error' with "
                    "a uniform fallback"
                )
            ident = identity if isinstance(identity, str) else identity_json(identity)
            messages_ref, bodies = _split_messages(request.messages)
            for h, body in bodies.items():
                if h not in self._messages_seen:
                    texts[h] = body
            rows.append(
                (
                    key,
                    result.source,
                    ident,
                    request.task,
                    request.cluster,
                    _floats_json(request.obs),
                    _enc_names(tuple(request.action_names)),
                    messages_ref,
                    result.raw,
                    _floats_json(belief.tolist()),
                    result.status,
                    float(result.latency_s) if result.latency_s is not None else None,
                    result.prompt_tokens,
                    result.completion_tokens,
                    _extra_json(result.extra),
                    1,
                    now,
                    now,
                )
            )
        return self._put_rows(rows, texts)

    def put(
        self,
        key: str,
        identity: Mapping[str, Any] | str,
        request: BeliefRequest,
        result: BeliefResult,
    ) -> int:
        """Write one answer (see :meth:`put_many`)."""
        return self.put_many([(key, identity, request, result)])

    def _put_rows(self, rows: list[tuple[Any, ...]], texts: dict[str, str]) -> int:
        if not rows:
            return 0

        def body(conn: sqlite3.Connection) -> int:
            conn.executemany(
                "INSERT OR IGNORE INTO texts (hash, body) VALUES (?, ?)", list(texts.items())
            )
            before = conn.total_changes
            conn.executemany(_UPSERT, rows)
            return conn.total_changes - before

        changed = self._write(body)
        self._messages_seen.update(texts)
        return int(changed)

    # -- maintenance -----------------------------------------------------------------
    def integrity_check(self) -> list[str]:
        """Run SQLite's ``PRAGMA integrity_check``.

        Returns:
            ``["ok"]`` for a sound file, else SQLite's list of problems.

        """
        return [str(r[0]) for r in self._read("PRAGMA integrity_check")]

    def checkpoint(self) -> None:
        """Fold the WAL into the main file (``PRAGMA wal_checkpoint(TRUNCATE)``)."""
        self._read("PRAGMA wal_checkpoint(TRUNCATE)")

    def stats(self) -> dict[str, Any]:
        """Count rows and sum latencies and tokens (``amuled beliefs stats``).

        Returns:
            A JSON-compatible dict: rows, rows per status / source+model / task+cluster,
            latency and token totals, file sizes.

        """
        total = len(self)
        by_status = dict(self._read("SELECT status, COUNT(*) FROM beliefs GROUP BY status"))
        by_model = [
            {"source": s, "model": m, "rows": n}
            for s, m, n in self._read(
                "SELECT source, json_extract(identity, '$.model'), COUNT(*) FROM beliefs "
                "GROUP BY 1, 2 ORDER BY 3 DESC"
            )
        ]
        by_cluster = [
            {"task": t, "cluster": c, "rows": n}
            for t, c, n in self._read(
                "SELECT task, cluster, COUNT(*) FROM beliefs GROUP BY 1, 2 ORDER BY 1, 2"
            )
        ]
        lat = self._read(
            "SELECT COUNT(latency_s), AVG(latency_s), SUM(latency_s), SUM(prompt_tokens), "
            "SUM(completion_tokens), SUM(attempts) FROM beliefs"
        )[0]
        files = {}
        if self.path != ":memory:":
            for suffix in ("", "-wal"):
                p = Path(self.path + suffix)
                files[p.name] = p.stat().st_size if p.exists() else 0
        return {
            "path": self.path,
            "open_mode": self.open_mode,
            "schema_version": SCHEMA_VERSION,
            "rows": total,
            "cacheable_rows": sum(n for s, n in by_status.items() if s in CACHEABLE),
            "by_status": by_status,
            "by_model": by_model,
            "by_task_cluster": by_cluster,
            "latency_s": {"count": lat[0], "mean": lat[1], "total": lat[2]},
            "tokens": {"prompt": lat[3] or 0, "completion": lat[4] or 0},
            "attempts": lat[5] or 0,
            "distinct_texts": int(self._read("SELECT COUNT(*) FROM texts")[0][0]),
            "identities": self.identities(),
            "file_bytes": files,
        }

    # -- export / import -------------------------------------------------------------
    def export_jsonl(
        self, fp: IO[str], *, status: Sequence[str] | None = None, task: str | None = None
    ) -> int:
        """Write rows as JSON Lines, one object per row (:meth:`StoredBelief.to_json`).

        Args:
            fp: A text file open for writing.
            status: Only these statuses (all when ``None``).
            task: Only this task (all when ``None``).

        Returns:
            The number of rows written.

        """
        count = 0
        for row in self.iter_rows(status=status, task=task):
            try:
                line = json.dumps(row.to_json(), ensure_ascii=False, allow_nan=False)
            except ValueError as error:  # a NaN/inf in a column other than the belief
                raise _bad_row(
                    f"{self.path}: row {row.key}", row.key, f"not standard JSON ({error})"
                ) from error
            fp.write(line + "\n")
            count += 1
        return count

    def import_jsonl(
        self, fp: IO[str], *, name: str = "<jsonl>", verify: bool = True, batch: int = 500
    ) -> dict[str, int]:
        """Read rows written by :meth:`export_jsonl` (from this or another machine).

        Rows follow the :meth:`put_many` rule: an existing answer is never replaced.

        Args:
            fp: A text file open for reading.
            name: The file's name, for error messages.
            verify: Recompute each key from the row's content and refuse a mismatch.
            batch: Rows per transaction.

        Returns:
            ``{"read": n, "written": m}`` (``m < n`` when answers were already there).

        Raises:
            BeliefStoreError: A line is not a valid row (names the file and line): not
                standard JSON (``NaN``, ``Infinity``, nested too deeply), a missing
                field, an unknown status, an invalid belief, a key that does not match.

        """
        read = written = 0
        rows: list[tuple[Any, ...]] = []
        texts: dict[str, str] = {}
        lineno = 0
        lines = iter(fp)
        while True:
            try:
                line = next(lines)
            except StopIteration:
                break
            except UnicodeDecodeError as error:
                raise BeliefStoreError(
                    f"{name}:{lineno + 1}: not UTF-8 text ({error}); export files are UTF-8"
                ) from None
            lineno += 1
            if not line.strip():
                continue
            row, bodies = _json_to_row(line, f"{name}:{lineno}", verify)
            rows.append(row)
            texts.update(bodies)
            read += 1
            if len(rows) >= batch:
                written += self._put_rows(rows, texts)
                rows, texts = [], {}
        written += self._put_rows(rows, texts)
        return {"read": read, "written": written}


@functools.lru_cache(maxsize=4096)
def _text_hash_cached(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _text_hash(text: str) -> str:
    """SHA-256 of a message body, memoising the long ones (shared prompt blocks)."""
    if len(text) < 256:
        return hashlib.sha256(text.encode("utf-8")).hexdigest()
    return _text_hash_cached(text)


def _split_messages(
    messages: Sequence[tuple[str, str]],
) -> tuple[str | None, dict[str, str]]:
    """Return the ``messages`` column (``[[role, text_hash], ...]``) and the bodies."""
    if not messages:
        return None, {}
    refs, bodies = [], {}
    for role, content in messages:
        h = _text_hash(content)
        refs.append(f'[{_enc(role)},"{h}"]')  # == canonical_json([[role, h], ...])
        bodies[h] = content
    return "[" + ",".join(refs) + "]", bodies


def _bad_row(where: str, key: str | None, problem: str) -> BeliefStoreError:
    """The error of a damaged store row: where, what was found, how to remove the row."""
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


def _why(error: BaseException) -> str:
    if isinstance(error, RecursionError):
        return "nested deeper than Python's JSON reader can follow"
    return str(error)


def _load_column(text: Any, column: str, where: str, key: str | None) -> Any:
    """Parse one JSON column of a stored row; a parse failure names the row."""
    try:
        return json.loads(text)
    except (TypeError, ValueError, RecursionError) as error:
        raise _bad_row(
            where, key, f"column {column!r} is not JSON ({_why(error)}): {show_values(text, 80)}"
        ) from None


def _load_extra(text: str | None, where: str, key: str) -> dict[str, Any]:
    """Parse the ``extra`` column (non-finite floats become ``"nan"``/``"inf"`` text)."""
    if not text or text == "{}":
        return {}
    value = _load_column(text, "extra", where, key)
    if not isinstance(value, dict):
        raise _bad_row(where, key, f"column 'extra' is not a JSON object: {show_values(text, 80)}")
    # rows of an older amuled-ma may hold NaN/Infinity (this one writes "nan"/"inf" text)
    return _plain(value) if "NaN" in text or "Infinity" in text else value


def _stored_belief(text: str, n_actions: int, where: str, key: str) -> np.ndarray:
    """Parse and check a stored belief; an invalid one names the row and the fix."""
    values = _load_column(text, "belief", where, key)
    belief, reason = check_belief(values, n_actions)
    if belief is None:
        raise _bad_row(where, key, f"belief {show_values(values)} {reason}; {RULE}")
    return belief


def _messages_refs(row: Sequence[Any], path: str) -> list[tuple[str, str]]:
    """The ``[[role, text_hash], ...]`` of a row's ``messages`` column, checked."""
    key = row[0]
    refs = _load_column(row[7], "messages", f"{path}: row {key}", key)
    if not isinstance(refs, list) or not all(
        isinstance(r, list) and len(r) == 2 and all(isinstance(x, str) for x in r) for r in refs
    ):
        raise _bad_row(
            f"{path}: row {key}", key, f"column 'messages' is not [[role, hash], ...]: {row[7]!r}"
        )
    return [(r, h) for r, h in refs]


def _row_to_stored(
    row: Sequence[Any], texts: Mapping[str, str] | None, path: str = "<store>"
) -> StoredBelief:
    (
        key,
        source,
        identity,
        task,
        cluster,
        obs,
        actions,
        messages_ref,
        raw,
        belief,
        status,
        latency,
        ptok,
        ctok,
        extra,
        attempts,
        created,
        updated,
    ) = row
    where = f"{path}: row {key}"
    messages: tuple[tuple[str, str], ...] | None = None
    if texts is not None:
        refs = _messages_refs(row, path) if messages_ref else []
        missing = [h for _, h in refs if h not in texts]
        if missing:
            raise _bad_row(where, key, f"message text {missing[0]} is not in table 'texts'")
        messages = tuple((r, texts[h]) for r, h in refs)
    obs_values = _load_column(obs, "obs", where, key)
    names = _load_column(actions, "actions", where, key)
    if not isinstance(names, list) or not names or not all(isinstance(a, str) for a in names):
        raise _bad_row(where, key, f"column 'actions' is not a list of names: {actions!r}")
    if not isinstance(obs_values, list) or not all(
        isinstance(x, int | float) and not isinstance(x, bool) for x in obs_values
    ):
        raise _bad_row(where, key, f"column 'obs' is not a list of numbers: {obs!r}")
    ident = _load_column(identity, "identity", where, key)
    return StoredBelief(
        key=key,
        source=source,
        identity=ident,
        task=task,
        cluster=cluster,
        obs=tuple(obs_values),
        action_names=tuple(names),
        messages=messages,
        raw=raw,
        belief=_stored_belief(belief, len(names), where, key),
        status=status,
        latency_s=latency,
        prompt_tokens=ptok,
        completion_tokens=ctok,
        extra=_load_extra(extra, where, key),
        attempts=int(attempts),
        created_at=float(created),
        updated_at=float(updated),
    )


def _finite_number(value: Any) -> bool:
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


def _json_to_row(line: str, where: str, verify: bool) -> tuple[tuple[Any, ...], dict[str, str]]:
    """Validate one exported JSON line and turn it into a table row."""
    try:
        obj = json.loads(line, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as error:
        raise BeliefStoreError(
            f"{where}: not JSON ({_why(error)}); each line must be one standard JSON object "
            "written by 'amuled beliefs export' (fix or remove the line)"
        ) from None
    if not isinstance(obj, dict):
        raise BeliefStoreError(
            f"{where}: expected a JSON object (one exported row), found {show_values(obj, 80)}"
        )
    required = ("key", "source", "identity", "task", "cluster", "obs", "actions", "belief")
    missing = [k for k in (*required, "status") if k not in obj]
    if missing:
        raise BeliefStoreError(f"{where}: missing field(s) {', '.join(missing)}")
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
    ident = identity_json(obj["identity"])
    if verify:
        expected = request_key(ident, request)
        if expected != obj["key"]:
            raise BeliefStoreError(
                f"{where}: key {obj['key'][:12]}... does not match the row's content "
                f"(expected {expected[:12]}...); the row was edited or written by another "
                "key version (import with --no-verify to keep it anyway)"
            )
    messages_ref, bodies = _split_messages(messages)
    now = time.time()
    try:
        row = (
            obj["key"],
            obj["source"],
            ident,
            request.task,
            request.cluster,
            canonical_json(list(request.obs)),
            canonical_json(list(request.action_names)),
            messages_ref,
            obj.get("raw"),
            canonical_json(belief.tolist()),
            obj["status"],
            obj.get("latency_s"),
            obj.get("prompt_tokens"),
            obj.get("completion_tokens"),
            _extra_json(obj.get("extra") or {}),
            int(obj.get("attempts") or 1),
            float(obj.get("created_at") or now),
            float(obj.get("updated_at") or now),
        )
    except (TypeError, ValueError) as error:
        raise BeliefStoreError(f"{at}: malformed row ({error})") from None
    return row, bodies
