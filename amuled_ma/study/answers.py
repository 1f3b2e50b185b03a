"""The participants' answers: one SQLite file (WAL, ``synchronous=FULL``) in the study folder.

``(participant, item)`` refuses a second answer; refusals are kept with their reason. Schema 2;
a version 1 file is migrated on open, and reads without ratings or expert answers unmigrated.
"""

from __future__ import annotations

import secrets
import sqlite3
import threading
import time
from contextlib import closing
from dataclasses import astuple, dataclass
from pathlib import Path

SCHEMA = """
CREATE TABLE IF NOT EXISTS participants (
    id TEXT PRIMARY KEY,
    token TEXT NOT NULL,
    source TEXT NOT NULL,          -- 'assigned' or the URL parameter it came from
    created REAL NOT NULL          -- Unix time
);
CREATE TABLE IF NOT EXISTS answers (
    participant TEXT NOT NULL REFERENCES participants(id),
    item TEXT NOT NULL,
    choice TEXT NOT NULL,          -- 'A' or 'B', as shown
    variant TEXT,                  -- the variant of the chosen option (NULL: attention check)
    correct INTEGER,               -- attention checks: 1 when the instructed option was chosen
    ms REAL NOT NULL,              -- time taken, measured by the page (jsPsych's rt)
    received REAL NOT NULL,        -- Unix time the server stored it
    rating_a INTEGER,              -- acceptability of option A, 1..points (NULL: not asked)
    rating_b INTEGER,              -- acceptability of option B
    PRIMARY KEY (participant, item)
);
CREATE TABLE IF NOT EXISTS expert_answers (
    participant TEXT NOT NULL REFERENCES participants(id),
    item TEXT NOT NULL,
    clarity INTEGER,               -- how clear the panel's reasons are (NULL: none stated)
    ms REAL NOT NULL,
    received REAL NOT NULL,
    PRIMARY KEY (participant, item)
);
CREATE TABLE IF NOT EXISTS expert_actions (
    participant TEXT NOT NULL,
    item TEXT NOT NULL,
    action INTEGER NOT NULL,       -- the task's action index
    acceptable INTEGER NOT NULL,   -- 1 acceptable, 0 not
    framework TEXT NOT NULL,       -- the framework that justifies it, or 'none'
    PRIMARY KEY (participant, item, action)
);
CREATE TABLE IF NOT EXISTS refusals (
    participant TEXT,
    item TEXT,
    choice TEXT,
    reason TEXT NOT NULL,
    received REAL NOT NULL
);
"""
#: The schema's version (``PRAGMA user_version``).
VERSION = 2
#: Columns added to ``answers`` by version 2, with their types.
RATING_COLUMNS = (("rating_a", "INTEGER"), ("rating_b", "INTEGER"))


@dataclass(frozen=True)
class Answer:
    """One stored answer to a pair or attention check; ratings None where none was asked."""

    participant: str
    item: str
    choice: str
    variant: str | None
    correct: int | None
    ms: float
    received: float
    rating_a: int | None = None
    rating_b: int | None = None


@dataclass(frozen=True)
class Judgement:
    """An expert's judgement of one action: acceptable or not, and the framework cited."""

    action: int
    acceptable: bool
    framework: str


@dataclass(frozen=True)
class ExpertAnswer:
    """One expert's answer about a state; ``clarity`` None where the panel stated no reason."""

    participant: str
    item: str
    clarity: int | None
    judgements: tuple[Judgement, ...]
    ms: float
    received: float


def _columns(db: sqlite3.Connection, table: str) -> set[str]:
    return {str(row[1]) for row in db.execute(f"PRAGMA table_info({table})")}


class AnswerStore:
    """The study's answers in SQLite (created when absent), safe from one server's threads."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("PRAGMA busy_timeout=10000")
        self._db.executescript(SCHEMA)
        have = _columns(self._db, "answers")  # a file of an earlier schema: its rows kept
        for name, kind in RATING_COLUMNS:
            if name not in have:
                self._db.execute(f"ALTER TABLE answers ADD COLUMN {name} {kind}")
        self._db.execute(f"PRAGMA user_version = {VERSION}")

    def close(self) -> None:
        """Close the connection."""
        with self._lock:
            self._db.close()

    def participant(self, wanted: str | None, source: str) -> tuple[str, str]:
        """A participant's ``(id, token)``: a new random id, or the one brought (same token)."""
        with self._lock:
            if wanted:
                row = self._db.execute(
                    "SELECT token FROM participants WHERE id = ?", (wanted,)
                ).fetchone()
                if row is not None:
                    return wanted, str(row[0])
                pid = wanted
            else:
                pid = "p-" + secrets.token_hex(8)
            token = secrets.token_urlsafe(18)
            self._db.execute(
                "INSERT INTO participants (id, token, source, created) VALUES (?, ?, ?, ?)",
                (pid, token, source, time.time()),
            )
            return pid, token

    def token_ok(self, participant: str, token: str) -> bool:
        """Whether ``token`` is the participant's."""
        with self._lock:
            row = self._db.execute(
                "SELECT token FROM participants WHERE id = ?", (participant,)
            ).fetchone()
        return row is not None and secrets.compare_digest(str(row[0]), str(token))

    def answered(self, participant: str) -> list[str]:
        """The items the participant has answered (pairs, attention checks, expert states)."""
        with self._lock:
            rows = self._db.execute(
                "SELECT item, received FROM answers WHERE participant = ? UNION ALL "
                "SELECT item, received FROM expert_answers WHERE participant = ? "
                "ORDER BY received",
                (participant, participant),
            ).fetchall()
        return [str(r[0]) for r in rows]

    def add(self, answer: Answer) -> bool:
        """Store an answer, committed before returning; False when already answered."""
        with self._lock:
            try:
                self._db.execute(
                    "INSERT INTO answers (participant, item, choice, variant, correct, ms, "
                    "received, rating_a, rating_b) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    astuple(answer),  # the fields in the columns' order
                )
            except sqlite3.IntegrityError:
                return False
            return True

    def add_expert(self, answer: ExpertAnswer) -> bool:
        """Store an expert's answer and judgements in one transaction; False if answered already."""
        with self._lock:
            try:
                with self._db:  # committed, or rolled back on any exception
                    self._db.execute("BEGIN IMMEDIATE")
                    self._db.execute(
                        "INSERT INTO expert_answers (participant, item, clarity, ms, received) "
                        "VALUES (?, ?, ?, ?, ?)",
                        (answer.participant, answer.item, answer.clarity, answer.ms,
                         answer.received),
                    )  # fmt: skip
                    self._db.executemany(
                        "INSERT INTO expert_actions (participant, item, action, acceptable, "
                        "framework) VALUES (?, ?, ?, ?, ?)",
                        [(answer.participant, answer.item, j.action, int(j.acceptable),
                          j.framework) for j in answer.judgements],
                    )  # fmt: skip
            except sqlite3.IntegrityError:
                return False
            return True

    def refuse(self, participant: str | None, item: str | None, choice: str | None, reason: str):
        """Keep a refused answer and why."""
        with self._lock:
            self._db.execute(
                "INSERT INTO refusals VALUES (?, ?, ?, ?, ?)",
                (participant, item, choice, reason, time.time()),
            )


def _read_only(path: Path) -> closing[sqlite3.Connection]:
    """A read-only connection to an answer file, closed on leaving its ``with``."""
    return closing(sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True))


def read_answers(path: Path) -> list[Answer]:
    """Every stored answer of a study's file, read-only (participant, then item order)."""
    with _read_only(path) as db:
        have = _columns(db, "answers")
        ratings = ", ".join(n if n in have else "NULL" for n, _ in RATING_COLUMNS)
        rows = db.execute(
            f"SELECT participant, item, choice, variant, correct, ms, received, {ratings} "
            "FROM answers ORDER BY participant, item"
        ).fetchall()
    return [Answer(*row) for row in rows]


def read_expert_answers(path: Path) -> list[ExpertAnswer]:
    """Every expert answer of a study's file, read-only (none in a version 1 file)."""
    with _read_only(path) as db:
        if not _columns(db, "expert_answers"):
            return []
        rows = db.execute(
            "SELECT participant, item, clarity, ms, received FROM expert_answers "
            "ORDER BY participant, item"
        ).fetchall()
        judged: dict[tuple[str, str], list[Judgement]] = {}
        for pid, item, action, acceptable, framework in db.execute(
            "SELECT participant, item, action, acceptable, framework FROM expert_actions "
            "ORDER BY participant, item, action"
        ):
            judged.setdefault((pid, item), []).append(
                Judgement(int(action), bool(acceptable), str(framework))
            )
    return [
        ExpertAnswer(pid, item, clarity, tuple(judged.get((pid, item), ())), ms, received)
        for pid, item, clarity, ms, received in rows
    ]


def read_refusals(path: Path) -> list[tuple[str | None, str | None, str | None, str]]:
    """Every refused answer ``(participant, item, choice, reason)``."""
    with _read_only(path) as db:
        rows = db.execute(
            "SELECT participant, item, choice, reason FROM refusals ORDER BY received"
        ).fetchall()
    return [tuple(r) for r in rows]
