"""The files that keep a distilled fine-tune's budget and training pairs across a resume.

``distill.json`` (the ledger, counters and generator) is replaced whole, and written before
a batch's asked states are sent, so the budget is spent first; ``distill-examples.jsonl``
gets one appended line per asked state (a line cut by a crash is ignored). Nothing here goes
into the belief store, which holds exactly the panel's answers.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from amuled_ma.beliefs.store.rows import why_not_json
from amuled_ma.errors import AmuledError
from amuled_ma.files.limits import check_size, read_bounded_bytes, read_line
from amuled_ma.files.safe import append_text, atomic_writer, checked_read_path

#: File of the budget ledger and counters.
LEDGER_FILE = "distill.json"
#: File of the training pairs (JSON Lines).
EXAMPLES_FILE = "distill-examples.jsonl"
#: Format tag of `LEDGER_FILE`.
FORMAT = "amuled-distill/1"
#: Seconds between two writes of the ledger when no state was asked.
SAVE_EVERY_S = 5.0
#: Largest counter a state file may hold (2**53: exact in JSON's doubles).
MAX_COUNTER = 2**53
#: Largest ledger read [bytes]: 35 a state visited, 70 + 20 an observation value a state
#: asked (measured); 1,000,000 asked of 10,000,000 visited is about 740 MB.
MAX_LEDGER_BYTES = 2**30
#: Largest training-pairs file read [bytes]: a line a state asked, 130 bytes to 1 KB;
#: 1,000,000 asked states is about 1 GB.
MAX_EXAMPLES_BYTES = 2**31
#: Longest line of the training-pairs file [bytes] (a fine-tune writes about 1 KB).
MAX_EXAMPLE_LINE_BYTES = 2**20
#: The fix of every refusal of a state file: they are this run's own files.
START_OVER = "start the fine-tune over with --force"
#: A state's key as a fine-tune writes it: a 128-bit BLAKE2b digest in hexadecimal.
STATE_KEY = re.compile(r"[0-9a-f]{32}")
#: Most values of one observation (the tasks' have 2 to 16).
MAX_OBS_DIM = 4096
#: Most panel members and actions a state file may name (a panel has a few of each).
MAX_NAMES = 256

_Finite = Annotated[float, Field(allow_inf_nan=False)]
_Counter = Annotated[int, Field(ge=0, le=MAX_COUNTER)]
_Name = Annotated[str, Field(min_length=1, max_length=200)]
_M = TypeVar("_M", bound=BaseModel)


class _Strict(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)


class _RngState(_Strict):
    state: int = Field(ge=0, lt=2**128)
    inc: int = Field(ge=0, lt=2**128)


class RngState(_Strict):
    """The random selection's generator, as numpy's ``PCG64.state`` writes it."""

    bit_generator: Literal["PCG64"]
    state: _RngState
    has_uint32: int = Field(ge=0, le=1)
    uinteger: int = Field(ge=0, lt=2**32)


class Counters(_Strict):
    """The counters of ``distill.json`` (those of ``DistillStats``)."""

    requests_forwarded: _Counter
    requests_sent: _Counter
    model_answers: _Counter
    miss_answers: _Counter
    unasked_answers: _Counter
    refits: _Counter

    @model_validator(mode="after")
    def _sent_were_forwarded(self) -> Counters:
        if self.requests_sent > self.requests_forwarded:
            raise ValueError(
                f"counters.requests_sent ({self.requests_sent}) exceeds "
                f"counters.requests_forwarded ({self.requests_forwarded})"
            )
        return self


class LedgerTable(_Strict):
    """``distill.json``'s ``ledger`` (`BudgetLedger.to_dict`; its invariant is `from_dict`'s)."""

    budget: float | int
    visited: list[str]
    asked: list[str]


class LedgerRest(BaseModel):
    """The fields of ``distill.json`` besides the settings and generation."""

    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    ledger: LedgerTable
    asked_obs: dict[str, list[_Finite]]
    members: list[_Name] = Field(max_length=MAX_NAMES)
    task: _Name | None = None
    actions: list[_Name] | None = Field(default=None, min_length=1, max_length=MAX_NAMES)
    obs_dim: int | None = Field(default=None, ge=1, le=MAX_OBS_DIM)
    rng: RngState | None = None
    counters: Counters

    @model_validator(mode="after")
    def _consistent(self) -> LedgerRest:
        for name, keys in (("visited", self.ledger.visited), ("asked", self.ledger.asked)):
            bad = next((key for key in keys if not STATE_KEY.fullmatch(key)), None)
            if bad is not None:
                raise ValueError(
                    f"ledger.{name} holds {bad[:40]!r}, not a state key (32 hexadecimal "
                    "digits, as a fine-tune writes them)"
                )
        for name, names in (("members", self.members), ("actions", self.actions or [])):
            if len(set(names)) != len(names):
                raise ValueError(f"{name} are not distinct: {names}")
        for key, obs in self.asked_obs.items():
            if not STATE_KEY.fullmatch(key):
                raise ValueError(f"asked_obs has a key {key[:40]!r}, not a state key")
            if len(obs) != self.obs_dim:
                raise ValueError(
                    f"asked_obs[{key}] has {len(obs)} values, but obs_dim is {self.obs_dim}"
                )
        return self


def checked(model: type[_M], data: object, where: str) -> _M:
    """``data`` validated as ``model``; else one `AmuledError` line naming ``where``, the field.

    The line holds pydantic's first error as ``field: message, found value`` (value cut to 60).
    """
    try:
        return model.model_validate(data)
    except ValidationError as error:
        first = error.errors()[0]
        field = ".".join(str(part) for part in first["loc"])
        message = str(first["msg"]).removeprefix("Value error, ")
        found = repr(first.get("input"))
        found = found if len(found) <= 60 else found[:57] + "..."
        head = f"{where}: {field}: " if field else f"{where}: "
        tail = "" if first["type"] == "value_error" else f", found {found}"
        raise AmuledError(
            f"{head}{message}{tail}; the file was edited or damaged; {START_OVER}"
        ) from None


class Example(_Strict):
    """One line of ``distill-examples.jsonl``; lengths and sums are checked by `DistilledSource`."""

    key: str = Field(pattern=STATE_KEY.pattern)
    obs: list[_Finite] = Field(max_length=MAX_OBS_DIM)
    beliefs: dict[_Name, list[_Finite]] = Field(max_length=MAX_NAMES)


class StateFiles:
    """The two state files of one fine-tune folder (created on the first write)."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)
        self.ledger = self.folder / LEDGER_FILE
        self.examples = self.folder / EXAMPLES_FILE
        self.saved_at = 0.0

    def load(self) -> dict[str, Any]:
        """Read the ledger (`UnsafePathError` on a link; `AmuledError`: too big, or not one)."""
        ledger = checked_read_path(self.folder, LEDGER_FILE)
        try:
            raw = read_bounded_bytes(
                ledger,
                MAX_LEDGER_BYTES,
                "budget state",
                note="a budget of 1,000,000 asked states is about 740 MB",
                fix=f"the file was edited or is not this run's; {START_OVER}",
            )
            data = json.loads(raw)
        except (OSError, ValueError, RecursionError) as error:
            raise AmuledError(
                f"{self.ledger}: not a readable budget state ({why_not_json(error)}); {START_OVER}"
            ) from error
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise AmuledError(
                f"{self.ledger}: not a budget state of format {FORMAT!r}; {START_OVER}"
            )
        return data

    def save(self, data: Mapping[str, Any]) -> None:
        """Write the ledger whole or not at all (UnsafePathError on a link; FileWriteError)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        with atomic_writer(self.ledger, text=True) as handle:
            json.dump({"format": FORMAT, **data}, handle, separators=(",", ":"))
        self.saved_at = time.monotonic()

    def append(self, records: Iterable[Mapping[str, Any]]) -> None:
        """Append training pairs, one JSON line each (UnsafePathError on a link, FileWriteError)."""
        lines = "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in records)
        if not lines:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        append_text(self.examples, lines)

    def read_examples(self) -> list[tuple[str, Example]]:
        """Every training pair written (a cut last line is skipped), with its ``FILE:LINE``.

        `AmuledError`: a line other than the last not an `Example`, or a file or line too long.
        """
        if not checked_read_path(self.folder, EXAMPLES_FILE).is_file():
            return []
        fix = f"the file was edited or is not this run's; {START_OVER}"
        out = []
        try:
            check_size(
                self.examples,
                MAX_EXAMPLES_BYTES,
                "training-pairs file",
                note="a budget of 1,000,000 asked states is about 1 GB",
                fix=fix,
            )
            with self.examples.open("rb") as handle:
                number = 0
                while line := read_line(
                    handle,
                    MAX_EXAMPLE_LINE_BYTES,
                    f"{self.examples}:{number + 1}",
                    unit="bytes",
                    fix=f"a line holds one state's pairs, about 1 KB; {fix}",
                ):
                    number += 1
                    try:
                        record = json.loads(line)
                    except (ValueError, RecursionError) as error:
                        if not line.endswith(b"\n") or not handle.peek(1):
                            break  # the last line, cut short by a crash while it was written
                        raise AmuledError(
                            f"{self.examples}:{number}: not JSON ({error}); {START_OVER}"
                        ) from None
                    where = f"{self.examples}:{number}"
                    out.append((where, checked(Example, record, where)))
        except OSError as error:
            raise AmuledError(
                f"{self.examples}: cannot read the training pairs ({error}); {START_OVER}"
            ) from error
        return out
