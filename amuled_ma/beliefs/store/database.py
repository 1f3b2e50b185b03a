"""The belief store: one SQLite row (WAL, busy timeout) per belief request ever answered.

Only `CACHEABLE` rows are served and never overwritten; other rows are kept and asked again.
A read-only open uses ``mode=ro``, else ``immutable=1`` where no ``-shm`` can be written.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import threading
import time
import urllib.parse
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from amuled_ma.beliefs.replies.validate import RULE, check_belief, show_values
from amuled_ma.beliefs.store.keys import identity_json
from amuled_ma.beliefs.store.rows import (
    CACHEABLE,
    COLUMNS,
    SCHEMA,
    SCHEMA_VERSION,
    BeliefStoreError,
    Row,
    StoredBelief,
    check_storable,
    damaged_row,
    decode_row,
    encode_row,
    load_belief,
    load_column,
    load_extra,
    message_refs,
    unstorable_text,
)
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult

#: Environment variable naming the default store file.
STORE_ENV = "AMULED_BELIEF_STORE"

_SQL_CHUNK = 500  # keys per ``IN (...)`` query, well under SQLite's variable limit

#: Longest value and row SQLite reads or writes in a store [bytes, 64 MiB;
#: ``SQLITE_LIMIT_LENGTH``]: 4 bytes (UTF-8's most) per character of the longest imported line
#: (`MAX_LINE_CHARS`, 16 Mi); SQLite refuses a longer value without reading it into memory.
MAX_VALUE_BYTES = 2**26


def _too_long(detail: str = "") -> str:
    """How every refusal of a too-long store value says it (``detail``: SQLite's words)."""
    why = f"{detail}; " if detail else ""
    return (
        f"longer than the {MAX_VALUE_BYTES:,} bytes a stored value may be ({why}an answer "
        "with its chat is about 20 KB)"
    )


#: One row to write: key, identity, request, answer, attempts, created_at, updated_at.
_Item = tuple[
    str, Mapping[str, Any] | str, BeliefRequest, BeliefResult | StoredBelief, int, float, float
]


class _ValueTooBig(BeliefStoreError):
    """A read met a value longer than `MAX_VALUE_BYTES` (SQLite's "too big")."""


# Insert, or replace a row that holds no answer yet; an ok/repaired row is never replaced.
_UPSERT = f"""
INSERT INTO beliefs ({COLUMNS}) VALUES ({", ".join("?" * 18)})
ON CONFLICT (key) DO UPDATE SET
    raw = excluded.raw, belief = excluded.belief, status = excluded.status,
    latency_s = excluded.latency_s, prompt_tokens = excluded.prompt_tokens,
    completion_tokens = excluded.completion_tokens, extra = excluded.extra,
    attempts = beliefs.attempts + excluded.attempts, updated_at = excluded.updated_at
WHERE beliefs.status NOT IN ('ok', 'repaired')
"""


def default_store_path() -> Path:
    """``$AMULED_BELIEF_STORE``, else ``$XDG_CACHE_HOME/amuled/beliefs.sqlite`` (``~/.cache``)."""
    env = os.environ.get(STORE_ENV)
    if env:
        return Path(env)
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "amuled" / "beliefs.sqlite"


class BeliefStore:
    """A SQLite file of belief answers, shared safely by threads and processes.

    ``path`` is created with its folder (``":memory:"``: a private store); a writer waits
    ``timeout_s`` for another process's lock; ``synchronous`` is ``"NORMAL"`` or ``"FULL"``
    (also power-loss safe); ``read_only`` opens an existing file and never writes (see the
    module doc). Raises `BeliefStoreError`: the file cannot be opened or is no belief store.
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

    def _connect(self) -> sqlite3.Connection:
        """Open (or, after a ``fork``, re-open) this process's connection."""
        if self._conn is not None and self._pid == os.getpid():
            return self._conn
        if self.read_only:
            return self._connect_read_only()
        if self.path != ":memory:":
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        try:
            conn = self._sqlite(self.path)
            if self.path != ":memory:":
                mode = self._journal_wal(conn)
                if str(mode).lower() != "wal":
                    raise BeliefStoreError(f"{self.path}: cannot switch to WAL mode (got {mode})")
            conn.execute(f"PRAGMA synchronous = {self.synchronous}")
            self._conn, self._pid = conn, os.getpid()
            self._messages_seen = set()
            self._write(self._create_schema)
        except (sqlite3.DatabaseError, BeliefStoreError) as error:
            self._conn = None
            cause = error if isinstance(error, sqlite3.DatabaseError) else error.__cause__
            if isinstance(cause, sqlite3.DatabaseError):  # also: creating the tables failed
                raise BeliefStoreError(f"{self.path}: cannot open belief store: {cause}") from cause
            raise
        return conn

    def _sqlite(self, target: str, *, uri: bool = False) -> sqlite3.Connection:
        """A connection to ``target`` with the busy timeout and `MAX_VALUE_BYTES` set."""
        conn = sqlite3.connect(
            target, uri=uri, timeout=self.timeout_s, isolation_level=None, check_same_thread=False
        )
        conn.execute(f"PRAGMA busy_timeout = {int(self.timeout_s * 1000)}")
        conn.setlimit(sqlite3.SQLITE_LIMIT_LENGTH, MAX_VALUE_BYTES)
        return conn

    def _journal_wal(self, conn: sqlite3.Connection) -> str:
        """Switch to WAL mode, waiting ``timeout_s`` for locks (SQLite's busy handler does not)."""
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
                conn = self._sqlite(f"file:{quoted}?{mode}", uri=True)
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
        for statement in SCHEMA.split(";"):
            if statement.strip():
                conn.execute(statement)
        conn.execute(
            "INSERT OR IGNORE INTO meta (name, value) VALUES ('schema_version', ?)",
            (str(SCHEMA_VERSION),),
        )
        BeliefStore._check_schema(conn)

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
            try:
                conn.execute("BEGIN IMMEDIATE")
                try:
                    out = body(conn)
                except BaseException:
                    with contextlib.suppress(sqlite3.Error):
                        conn.execute("ROLLBACK")
                    raise
                conn.execute("COMMIT")
            except sqlite3.DataError as error:  # "string or blob too big"
                raise BeliefStoreError(
                    f"{self.path}: cannot write the belief store: a value is "
                    f"{_too_long(str(error))}; nothing of this batch was written"
                ) from error
            except sqlite3.DatabaseError as error:
                # a damaged file ("database disk image is malformed"), a full disk
                raise BeliefStoreError(
                    f"{self.path}: cannot write the belief store: {error}; nothing of this "
                    "batch was written; if the disk is full, free some space; if the file "
                    "is damaged, move it away and rebuild it from an export ('amuled "
                    "beliefs import'), or delete it (every belief is then asked again)"
                ) from error
            return out

    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            try:
                return self._connect().execute(sql, params).fetchall()
            except sqlite3.DataError as error:  # "string or blob too big": not read
                raise _ValueTooBig(
                    str(
                        damaged_row(
                            str(self.path),
                            None,
                            f"a row holds a value {_too_long(str(error))}; it is not read",
                        )
                    )
                ) from error
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

    def get_many(
        self, keys: Iterable[str], *, cacheable_only: bool = True, with_messages: bool = False
    ) -> dict[str, StoredBelief]:
        """Read the rows of ``keys`` that exist as ``{key: row}`` (duplicate keys allowed).

        ``cacheable_only`` returns only answers (``ok``/``repaired``); ``with_messages`` also reads
        each row's chat (slower; ``messages`` is ``None`` otherwise).
        """
        found: dict[str, StoredBelief] = {}
        for rows in self._by_keys(COLUMNS, keys, cacheable_only):
            texts = self._texts(rows) if with_messages else None
            found.update((row[0], decode_row(row, texts, self.path)) for row in rows)
        return found

    def _by_keys(
        self, columns: str, keys: Iterable[str], cacheable_only: bool
    ) -> Iterator[list[tuple[Any, ...]]]:
        """The ``columns`` of the rows of ``keys`` (each once), a list per `_SQL_CHUNK` keys.

        A too-long value's error names its row.
        """
        wanted = list(dict.fromkeys(keys))
        status = " AND status IN ('ok', 'repaired')" if cacheable_only else ""
        for start in range(0, len(wanted), _SQL_CHUNK):
            chunk = wanted[start : start + _SQL_CHUNK]
            marks = ",".join("?" * len(chunk))
            try:
                rows = self._read(
                    f"SELECT {columns} FROM beliefs WHERE key IN ({marks}){status}", chunk
                )
            except _ValueTooBig:
                for key in chunk:
                    try:
                        self._read(f"SELECT {columns} FROM beliefs WHERE key = ?{status}", [key])
                    except _ValueTooBig:
                        raise damaged_row(
                            f"{self.path}: row {key}", key, f"a value {_too_long()}; it is not read"
                        ) from None
                raise
            yield rows

    def _texts(self, rows: Sequence[Sequence[Any]]) -> dict[str, str]:
        """Fetch the message bodies referenced by ``rows``."""
        hashes = {h for row in rows if row[7] for _, h in message_refs(row, self.path)}
        texts = {h: self._text_cache[h] for h in hashes if h in self._text_cache}
        todo = [h for h in hashes if h not in texts]
        for start in range(0, len(todo), _SQL_CHUNK):
            chunk = todo[start : start + _SQL_CHUNK]
            sql = f"SELECT hash, body FROM texts WHERE hash IN ({','.join('?' * len(chunk))})"
            texts.update(self._read(sql, chunk))
        if len(self._text_cache) > 4096:
            self._text_cache.clear()
        # keep the bodies shared by many rows (system prompt, few-shot turns) at hand
        for h, body in texts.items():
            if len(body) > 2000:
                self._text_cache[h] = body
        return texts

    def lookup(self, keys: Iterable[str]) -> dict[str, BeliefResult]:
        """The answers (``ok``/``repaired`` rows) of ``keys`` as cache hits (`CachedSource`'s path).

        Only a `BeliefResult`'s columns are read; ``cached=True``, ``latency_s=0`` and the
        original latency in ``extra["stored_latency_s"]``.
        """
        found: dict[str, BeliefResult] = {}
        columns = "key, source, raw, belief, status, latency_s, prompt_tokens, completion_tokens"
        for rows in self._by_keys(f"{columns}, extra, actions", keys, True):
            for key, source, raw, belief, status, lat, ptok, ctok, extra, actions in rows:
                where = f"{self.path}: row {key}"
                n = self._width.get(actions)
                if n is None:
                    names = load_column(actions, "actions", where, key)
                    if not isinstance(names, list) or not names:
                        problem = f"actions is not a list of names: {actions!r}"
                        raise damaged_row(where, key, problem)
                    n = self._width[actions] = len(names)
                info = load_extra(extra, where, key)
                info["stored_latency_s"] = lat
                found[key] = BeliefResult(
                    belief=load_belief(belief, n, where, key),
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
        """Read one row, chat included by default, or ``None`` (see `get_many`)."""
        rows = self.get_many([key], cacheable_only=cacheable_only, with_messages=with_messages)
        return rows.get(key)

    def iter_rows(
        self, *, status: Sequence[str] | None = None, task: str | None = None
    ) -> Iterator[StoredBelief]:
        """Iterate over the rows of ``status`` and ``task`` (all when None), oldest first."""
        where: list[str] = []
        params: list[str] = []
        if status:
            where.append(f"status IN ({','.join('?' * len(status))})")
            params.extend(status)
        if task:
            where.append("task = ?")
            params.append(task)
        sql = f"SELECT {COLUMNS} FROM beliefs WHERE {' AND '.join(where) or '1'}"
        rows = self._read(f"{sql} ORDER BY created_at, rowid", params)
        for start in range(0, len(rows), _SQL_CHUNK):
            chunk = rows[start : start + _SQL_CHUNK]
            texts = self._texts(chunk)
            for row in chunk:
                yield decode_row(row, texts, self.path)

    def identities(self) -> list[dict[str, Any]]:
        """``[{"identity": {...}, "rows": n, "answers": m}, ...]``, most rows first."""
        rows = self._read(
            "SELECT identity, COUNT(*), SUM(status IN ('ok', 'repaired')) FROM beliefs "
            "GROUP BY identity ORDER BY 2 DESC"
        )
        out = []
        for ident, n, m in rows:
            where = f"{self.path}: identity {ident[:60]!r}"
            identity = load_column(ident, "identity", where, None)
            out.append({"identity": identity, "rows": n, "answers": int(m or 0)})
        return out

    def request_seconds(self, model: str) -> list[float]:
        """``latency_s`` above 0 of each answer of ``model`` (the identity's), oldest first."""
        rows = self._read(
            "SELECT latency_s FROM beliefs WHERE status IN ('ok', 'repaired') AND latency_s > 0 "
            "AND json_extract(identity, '$.model') = ? ORDER BY created_at, rowid",
            (model,),
        )
        return [float(latency) for (latency,) in rows]

    def __len__(self) -> int:
        return int(self._read("SELECT COUNT(*) FROM beliefs")[0][0])

    def __contains__(self, key: object) -> bool:
        return bool(self._read("SELECT 1 FROM beliefs WHERE key = ?", (key,)))

    def put_many(
        self, items: Iterable[tuple[str, Mapping[str, Any] | str, BeliefRequest, BeliefResult]]
    ) -> int:
        """Write ``(key, identity, request, result)`` answers in one transaction; return the count.

        ``identity``: ``identity()`` or its `identity_json` text. An ``ok``/``repaired`` row is
        kept; another is replaced, its ``attempts`` counted up. An invalid belief raises
        `BeliefStoreError` and nothing of the batch is written.
        """
        now = time.time()
        return self._put([(k, ident, req, res, 1, now, now) for k, ident, req, res in items])

    def put_rows(self, records: Iterable[StoredBelief]) -> int:
        """Write whole rows (`import_jsonl`) as `put_many` does, keeping attempts and timestamps."""
        return self._put(
            [
                (r.key, r.identity, r.request(), r, r.attempts, r.created_at, r.updated_at)
                for r in records
            ]
        )

    def _put(self, items: list[_Item]) -> int:
        """Check, encode and write ``items`` in one transaction; return the rows changed."""
        rows: list[Row] = []
        texts: dict[str, str] = {}
        for key, identity, request, answer, attempts, created_at, updated_at in items:
            belief, reason = check_belief(answer.belief, len(request.action_names))
            if belief is None:
                raise BeliefStoreError(
                    f"{self.path}: refusing to write row {key} ({request.task} / "
                    f"{request.cluster}, status {answer.status!r}, source {answer.source!r}): "
                    f"belief {show_values(answer.belief)} {reason}; {RULE}; pass a source's "
                    "answers through CachedSource (or amuled_ma.beliefs.replies.validate."
                    "checked_result), which turns an invalid answer into status 'error' with "
                    "a uniform fallback"
                )
            ident = identity if isinstance(identity, str) else identity_json(identity)
            reason = unstorable_text(request.messages, "messages")  # hashed as UTF-8 below
            if reason is not None:
                raise self._refuse(key, reason)
            row, bodies = encode_row(
                key, ident, request, belief, answer, attempts, created_at, updated_at
            )
            rows.append(row)
            texts.update((h, b) for h, b in bodies.items() if h not in self._messages_seen)
        if not rows:
            return 0

        def body(conn: sqlite3.Connection) -> int:
            conn.executemany(
                "INSERT OR IGNORE INTO texts (hash, body) VALUES (?, ?)", list(texts.items())
            )
            before = conn.total_changes
            conn.executemany(_UPSERT, rows)
            return conn.total_changes - before

        for row in rows:  # a lone surrogate would fail mid-transaction in SQLite
            reason = check_storable(row)
            if reason is not None:
                raise self._refuse(str(row[0]), reason)
        for text in texts.values():
            reason = unstorable_text(text, "a message")
            if reason is not None:
                raise self._refuse("of this batch", reason)
        changed = self._write(body)
        self._messages_seen.update(texts)
        return int(changed)

    def _refuse(self, key: str, reason: str) -> BeliefStoreError:
        """The one line of a row whose text cannot be stored (nothing of the batch is)."""
        return BeliefStoreError(
            f"{self.path}: refusing to write row {key}: {reason}; nothing of this batch was "
            "written (fix the text at its source: a file or a reply that is not UTF-8)"
        )

    def integrity_check(self) -> list[str]:
        """SQLite's ``PRAGMA integrity_check``: ``["ok"]`` for a sound file, else its problems."""
        return [str(r[0]) for r in self._read("PRAGMA integrity_check")]

    def checkpoint(self) -> None:
        """Fold the WAL into the main file (``PRAGMA wal_checkpoint(TRUNCATE)``)."""
        self._read("PRAGMA wal_checkpoint(TRUNCATE)")

    def stats(self) -> dict[str, Any]:
        """Counts and sums for ``amuled beliefs stats``, as a JSON-compatible dict."""
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
