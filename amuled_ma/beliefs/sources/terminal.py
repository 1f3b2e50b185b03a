"""``terminal``: a person types a member's beliefs, a line a state (``docs/beliefs.md``)."""

from __future__ import annotations

import contextlib
import io
import math
import re
import sys
import time
from collections.abc import Iterator, Sequence
from typing import IO, Any

import numpy as np

from amuled_ma.beliefs.replies.validate import check_belief
from amuled_ma.beliefs.store.rows import unstorable_text
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, in_order, indices_by
from amuled_ma.errors import ScenarioError
from amuled_ma.monitor.progress import held
from amuled_ma.tasks.pictures import state_picture

#: The answer that abstains on purpose.
SKIP = "skip"
#: The answer that shows the full prompt and asks again.
PROMPT = "prompt"
#: Most answer lines read per state (``attempts`` may not exceed it).
MAX_ATTEMPTS = 100
#: Longest answer line read (characters); a longer line is refused.
MAX_LINE_CHARS = 10_000
#: Most digits of a typed action index (an index is below the action count; Python's
#: ``int`` refuses a text of more than 4,300 digits with an error of its own).
MAX_INDEX_DIGITS = 20

_SPLIT = re.compile(r"[\s,;]+")
#: What :meth:`TerminalSource._read` returns for a line the input's decoder refused.
_UNDECODABLE_MARK = "\x00undecodable:"
_UNDECODABLE = _UNDECODABLE_MARK + "{} at byte {}"


def _printable(line: str) -> str:
    r"""The line with undecodable bytes as ``\udcNN`` escapes (text the store can hold)."""
    if line.startswith(_UNDECODABLE_MARK):
        return "<not UTF-8: " + line[len(_UNDECODABLE_MARK) :] + ">"
    return line.encode("utf-8", "backslashreplace").decode("utf-8")


def _cut(token: str) -> str:
    """A typed token as the reason quotes it: its first 40 characters and its length."""
    return repr(token) if len(token) <= 40 else f"{token[:40]!r}... ({len(token):,} characters)"


def action_by_name(text: str, action_names: Sequence[str]) -> tuple[int | None, list[str]]:
    """The action typed ``text`` stands for: its whole name or the start of one, any case.

    Returns ``(index, [])`` for one action (a whole name wins over a longer name it starts);
    ``(None, names)`` with the actions it starts when more than one; ``(None, [])`` for none.
    """
    typed = text.strip().casefold()
    if not typed:
        return None, []
    names = [name.casefold() for name in action_names]
    if typed in names:
        return names.index(typed), []
    starts = [i for i, name in enumerate(names) if name.startswith(typed)]
    if len(starts) == 1:
        return starts[0], []
    return None, [action_names[i] for i in starts]


def parse_answer(
    line: str, n_actions: int, action_names: Sequence[str] = ()
) -> tuple[np.ndarray | None, str | None]:
    """Read one typed answer (``action_names`` empty: an action is given by index only).

    Returns ``(belief, None)``, ``(None, None)`` for ``skip``, or ``(None, reason)`` for an
    answer that is refused (the reason says what was found and what is expected).
    """
    text = line.strip()
    if text.lower() == SKIP:
        return None, None
    by_name = f", an action name ({', '.join(action_names)})" if action_names else ""
    expected = (
        f"expected {n_actions} non-negative numbers (one per action, e.g. "
        f"{' '.join(['0.25'] * n_actions) if n_actions <= 8 else '0.5 0.5 0 ...'}), "
        f"an action index 0..{n_actions - 1}{by_name}, or {SKIP}"
    )
    if not text:
        return None, f"found an empty line; {expected}"
    if len(text) > MAX_LINE_CHARS:
        return None, f"found a line of {len(text)} characters; {expected}"
    if action_names and any(c.isalpha() for c in text):
        index, alike = action_by_name(text, action_names)
        if index is not None:
            return np.eye(n_actions)[index], None  # all on the named action
        if alike:
            return None, f"found {_cut(text)}, the start of {' and '.join(alike)}; {expected}"
    tokens = [t for t in _SPLIT.split(text) if t]
    if len(tokens) == 1 and re.fullmatch(r"[+-]?\d+", tokens[0]):
        if len(tokens[0]) > MAX_INDEX_DIGITS:  # int() of thousands of digits raises
            return None, (
                f"found an action index of {len(tokens[0]):,} digits, out of range; {expected}"
            )
        index = int(tokens[0])
        if not 0 <= index < n_actions:
            return None, f"found the action index {index}, out of range; {expected}"
        return np.eye(n_actions)[index], None
    values: list[float] = []
    for token in tokens:
        try:
            value = float(token)
        except ValueError:
            return None, f"found {_cut(token)}, not a number; {expected}"
        if not math.isfinite(value):
            return None, f"found {_cut(token)}, not a finite number; {expected}"
        values.append(value)
    checked, reason = check_belief(values, n_actions, scores=True)
    if checked is None:
        return None, f"the answer {reason}; {expected}"
    return checked, None


class TerminalSource(BeliefSource):
    """Beliefs typed by a person, one line per state (``docs/beliefs.md``, "terminal").

    ``person`` is part of `identity`; ``attempts`` lines (1 to `MAX_ATTEMPTS`) are read per
    state; ``stdin`` / ``stdout`` default to ``sys.stdin`` / ``sys.stderr``. `ScenarioError`:
    ``attempts`` out of range or ``person`` empty.
    """

    name = "terminal"
    #: The state prompt is shown to the person, so the panel renders it.
    needs_messages = True

    def __init__(
        self,
        *,
        person: str = "human",
        attempts: int = 3,
        stdin: IO[str] | None = None,
        stdout: IO[str] | None = None,
    ) -> None:
        if isinstance(attempts, bool) or not isinstance(attempts, int):
            raise ScenarioError(f"terminal source: attempts expects an integer, found {attempts!r}")
        if not 1 <= attempts <= MAX_ATTEMPTS:
            raise ScenarioError(
                f"terminal source: attempts expects an integer in [1, {MAX_ATTEMPTS}] "
                f"(answer lines read per state), found {attempts}"
            )
        if not isinstance(person, str) or not person.strip():
            raise ScenarioError(
                f"terminal source: person expects a non-empty name, found {person!r}"
            )
        self.person = person
        self.attempts = attempts
        self._stdin = stdin
        self._stdout = stdout
        #: Set once the input stream has ended; every later request abstains unread.
        self.eof = False
        #: The states this person will be asked in all (the ``n`` of "state k of n"), set
        #: by whoever knows it (a budget of states); None: not known ahead.
        self.expected: int | None = None
        #: Counters: ``asked`` states shown, ``answered``, ``skipped``, ``invalid`` lines
        #: refused, ``gave_up`` states abstained after ``attempts`` invalid lines,
        #: ``eof`` states abstained because the input had ended.
        self.stats: dict[str, int] = dict.fromkeys(
            ("asked", "answered", "skipped", "invalid", "gave_up", "eof"), 0
        )

    def identity(self) -> dict[str, Any]:
        """Return the kind and the person (what decides the answers)."""
        return {"source": self.name, "person": self.person}

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Ask for every request in turn; see the module docstring."""
        return in_order(self.iter_beliefs(requests), len(requests), self.name)

    def iter_beliefs(self, requests: Sequence[BeliefRequest]) -> Iterator[tuple[int, BeliefResult]]:
        """Yield ``(index, result)`` as each answer is typed; duplicates get copies of the first."""
        groups = indices_by(requests, lambda r: r)
        for position, (request, indices) in enumerate(groups.items(), start=1):
            with held():  # no progress line or bar redraw over the question
                result = self._question(request, len(groups) - position)
            for j, index in enumerate(indices):
                yield index, result if j == 0 else result.copy()

    def _write(self, text: str) -> None:
        stream = self._stdout if self._stdout is not None else sys.stderr
        stream.write(text)
        stream.flush()

    def _read(self) -> str | None:
        stream = self._stdin if self._stdin is not None else sys.stdin
        if stream is None:  # pragma: no cover - pythonw, a daemon without stdin
            return None
        if isinstance(stream, io.TextIOWrapper) and stream.errors == "strict":
            # a strict decoder would drop a whole buffered chunk on one stray byte: read
            # bytes that are not UTF-8 as lone surrogates, refused line by line below
            with contextlib.suppress(ValueError, OSError, AttributeError):
                stream.reconfigure(errors="surrogateescape")
        try:
            line = stream.readline(MAX_LINE_CHARS + 2)
        except UnicodeDecodeError as error:  # a byte that is not text: refused, asked again
            return _UNDECODABLE.format(error.reason, error.start)
        except (OSError, ValueError):  # a closed or unreadable stream is an end of input
            return None
        return line if line else None

    def _show(self, request: BeliefRequest, left: int) -> None:
        number, total = self.stats["asked"], self.expected
        if total is not None and number <= total:
            of = f" of {total}"
        else:  # the total is not known ahead: what this batch still holds
            of = f" ({left} more now)" if left else ""
        lines = [
            "",
            f"== {self.person}: agent {request.cluster!r}, task {request.task!r}, "
            f"state {number}{of} ==",
        ]
        picture = state_picture(request.task, request.obs)
        if picture is not None:
            lines.append(picture)
        elif request.messages:
            lines.append(request.messages[-1][1].rstrip())
        else:
            lines.append(f"observation: {', '.join(f'{x:g}' for x in request.obs)}")
        lines.append(
            "actions: " + " | ".join(f"{i}: {name}" for i, name in enumerate(request.action_names))
        )
        full = f", or {PROMPT} to see the full prompt" if request.messages else ""
        lines.append(
            f"answer with {request.num_actions} probabilities (e.g. "
            f"{' '.join(['0.25'] * request.num_actions) if request.num_actions <= 8 else '...'}"
            f"), an action index or name, or {SKIP}{full}"
        )
        self._write("\n".join(lines) + "\n")

    def _abstain(
        self, request: BeliefRequest, reason: str, raw: str | None, start: float
    ) -> BeliefResult:
        latency = time.perf_counter() - start
        n = request.num_actions
        return BeliefResult.failed(
            n, "abstained", self.name, reason, raw=raw, latency_s=latency, person=self.person
        )

    def _question(self, request: BeliefRequest, left: int) -> BeliefResult:
        start = time.perf_counter()
        n = request.num_actions
        if self.eof:
            self.stats["eof"] += 1
            return self._abstain(request, self._eof_reason(), None, start)
        self.stats["asked"] += 1
        self._show(request, left)
        last = None
        attempt = 0
        while attempt < self.attempts:
            self._write("belief> ")
            line = self._read()
            if line is None:
                self.eof = True
                self.stats["eof"] += 1
                self._write("\n(end of input: no answer)\n")
                return self._abstain(request, self._eof_reason(), last, start)
            last = line.rstrip("\r\n")
            if last.strip().lower() == PROMPT:  # shown, then asked again: not an attempt
                shown = f"(no prompt: the panel sent the observation only, {list(request.obs)})"
                if request.messages:
                    shown = request.messages[-1][1].rstrip()
                self._write(shown + "\n")
                continue
            attempt += 1
            belief, reason = parse_answer(last, n, request.action_names)
            if line.startswith(_UNDECODABLE_MARK) or unstorable_text(last) is not None:
                # bytes that are not UTF-8 (read as lone surrogates, or refused by the
                # decoder): the store could not hold the line, so it is not an answer
                last = _printable(last)
                belief, reason = (
                    None,
                    (
                        f"found bytes that are not UTF-8 text ({last[:80]}); type the answer "
                        "again (numbers, an action index or skip)"
                    ),
                )
            if belief is not None:
                self.stats["answered"] += 1
                return BeliefResult(
                    belief=belief,
                    status="ok",
                    source=self.name,
                    raw=last,
                    latency_s=time.perf_counter() - start,
                    extra={"person": self.person, "attempts": attempt},
                )
            if reason is None:
                self.stats["skipped"] += 1
                return self._abstain(request, f"skipped by {self.person}", last, start)
            self.stats["invalid"] += 1
            left = self.attempts - attempt
            self._write(f"not read: {reason} ({left} attempt{'s' if left != 1 else ''} left)\n")
        self.stats["gave_up"] += 1
        return self._abstain(
            request,
            f"{self.attempts} invalid answer(s) from {self.person}; the last: {last!r}",
            last,
            start,
        )

    def _eof_reason(self) -> str:
        return (
            f"the input of the terminal source ({self.person}) has ended (stdin closed or "
            "not a terminal); run the job in this process (amuled ... --jobs 1) at a "
            "terminal, or pipe the answers in, one line per state"
        )
