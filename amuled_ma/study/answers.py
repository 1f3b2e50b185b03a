"""The participants' answers: one SQLite file (WAL) in the study folder.

Every answer is committed before the server replies (``synchronous=FULL``), so an answer
the participant saw accepted survives the server being killed. A participant answers an
item once: the table's primary key ``(participant, item)`` refuses a second answer, and
the refusal is kept in ``refusals`` (with the reason), as is every tampered form.
"""

from __future__ import annotations

import secrets
import sqlite3
import threading
import time
from dataclasses import dataclass
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
    PRIMARY KEY (participant, item)
);
CREATE TABLE IF NOT EXISTS refusals (
    participant TEXT,
    item TEXT,
    choice TEXT,
    reason TEXT NOT NULL,
    received REAL NOT NULL
);
"""


@dataclass(frozen=True)
class Answer:
    """One stored answer (a row of ``answers``)."""

    participant: str
    item: str
    choice: str
    variant: str | None
    correct: int | None
    ms: float
    received: float


class AnswerStore:
    """The study's answers in SQLite (WAL), safe from several threads of one server.

    Args:
        path: The SQLite file (created with its tables when absent).

    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("PRAGMA busy_timeout=10000")
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        """Close the connection."""
        with self._lock:
            self._db.close()

    def participant(self, wanted: str | None, source: str) -> tuple[str, str]:
        """A participant's ``(id, token)``: a new id, or the one brought in the URL.

        An id brought from a recruiting platform gets the same token each time it comes
        back (the platform's id is the credential); an assigned id is a fresh random one.
        """
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
        """The items the participant has answered."""
        with self._lock:
            rows = self._db.execute(
                "SELECT item FROM answers WHERE participant = ? ORDER BY received", (participant,)
            ).fetchall()
        return [str(r[0]) for r in rows]

    def add(self, answer: Answer) -> bool:
        """Store an answer, committed before returning; False when already answered."""
        with self._lock:
            try:
                self._db.execute(
                    "INSERT INTO answers VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (answer.participant, answer.item, answer.choice, answer.variant,
                     answer.correct, answer.ms, answer.received),
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


def read_answers(path: Path) -> list[Answer]:
    """Every stored answer of a study's file, read-only (participant, then item order)."""
    db = sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True)
    try:
        rows = db.execute(
            "SELECT participant, item, choice, variant, correct, ms, received FROM answers "
            "ORDER BY participant, item"
        ).fetchall()
    finally:
        db.close()
    return [Answer(*row) for row in rows]


def read_refusals(path: Path) -> list[tuple[str | None, str | None, str | None, str]]:
    """Every refused answer ``(participant, item, choice, reason)``."""
    db = sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True)
    try:
        rows = db.execute(
            "SELECT participant, item, choice, reason FROM refusals ORDER BY received"
        ).fetchall()
    finally:
        db.close()
    return [tuple(r) for r in rows]  # type: ignore[misc]
