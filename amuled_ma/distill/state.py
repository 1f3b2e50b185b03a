"""The files that keep a distilled fine-tune's budget and training pairs across a resume.

In the fine-tune's folder:

- ``distill.json``: the settings, the budget ledger (every distinct state visited, the
  states asked in order, their observations), the panel members and actions, the number
  of refits, the counters and the random selection's generator. Written whole to a
  temporary file and moved over the old one (``os.replace``), so a crash leaves the old
  or the new file, never half of one. It is written **before** a batch's asked states are
  sent to the panel (the budget is spent first), after a batch that changed anything at
  most every :data:`SAVE_EVERY_S` seconds, and when the feedback is closed.
- ``distill-examples.jsonl``: the training pairs, one JSON line per asked state as its
  answers arrive (observation, each member's belief; appended, never rewritten). A line
  cut short by a crash is the last one and is ignored; the state is asked again from
  the store (a cache hit) the next time it is visited.

Nothing here is written into the belief store: the store holds exactly the panel's
answers to the asked states. Both files are written and read back through
:mod:`amuled_ma.files.safe`: never through a link, only regular files inside the folder.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from amuled_ma.errors import AmuledError
from amuled_ma.files.limits import check_size, read_bounded_bytes, read_line
from amuled_ma.files.safe import append_text, atomic_writer, checked_read_path

#: File of the budget ledger and counters.
LEDGER_FILE = "distill.json"
#: File of the training pairs (JSON Lines).
EXAMPLES_FILE = "distill-examples.jsonl"
#: Format tag of :data:`LEDGER_FILE`.
FORMAT = "amuled-distill/1"
#: Seconds between two writes of the ledger when no state was asked.
SAVE_EVERY_S = 5.0
#: Largest counter a state file may hold (2**53: exact in JSON's doubles).
MAX_COUNTER = 2**53
#: Largest ledger read [bytes, 1 GiB]. It grows with the states: 35 bytes a distinct state
#: visited, and 70 bytes plus about 20 an observation value a state asked (measured), so
#: a budget of 1,000,000 states asked of 10,000,000 visited, of 16-value observations, is
#: about 740 MB; it is read whole, and the run held the same in memory.
MAX_LEDGER_BYTES = 2**30
#: Largest training-pairs file read [bytes, 2 GiB]: one line a state asked, about 130
#: bytes for a 2-value observation and 2 members of 4 actions, 1 KB for 16 values and 5
#: members of 5 actions: a budget of 1,000,000 asked states is about 1 GB. It is read a
#: line at a time.
MAX_EXAMPLES_BYTES = 2**31
#: Longest line of the training-pairs file [bytes]: one state's observation and each
#: member's belief, about 1 KB (above); a longer line was not written by a fine-tune.
MAX_EXAMPLE_LINE_BYTES = 2**20
#: The fix of every refusal of a state file: they are this run's own files.
_START_OVER = "start the fine-tune over with --force"
#: A state's key as a fine-tune writes it: a 128-bit BLAKE2b digest in hexadecimal.
STATE_KEY = re.compile(r"[0-9a-f]{32}")
#: Most values of one observation (the tasks' have 2 to 16; a request holds the whole
#: observation, so a larger one is not a fine-tune's).
MAX_OBS_DIM = 4096
#: Most panel members and actions a state file may name (a panel has a few of each).
MAX_NAMES = 256

_Finite = Annotated[float, Field(allow_inf_nan=False)]
_Name = Annotated[str, Field(min_length=1, max_length=200)]


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


class LedgerRest(BaseModel):
    """The fields of ``distill.json`` besides the settings, ledger, counters and generation.

    Each observation is a list of :data:`MAX_OBS_DIM` finite numbers at most, all of
    length ``obs_dim``; the members and actions are distinct names; the generator's words
    are numpy's ranges. :func:`check_ledger_rest` turns a failure into one line.
    """

    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    asked_obs: dict[str, list[_Finite]]
    members: list[_Name] = Field(max_length=MAX_NAMES)
    task: _Name | None = None
    actions: list[_Name] | None = Field(default=None, min_length=1, max_length=MAX_NAMES)
    obs_dim: int | None = Field(default=None, ge=1, le=MAX_OBS_DIM)
    rng: RngState | None = None

    @model_validator(mode="after")
    def _consistent(self) -> LedgerRest:
        if len(set(self.members)) != len(self.members):
            raise ValueError(f"members are not distinct: {self.members}")
        if self.actions is not None and len(set(self.actions)) != len(self.actions):
            raise ValueError(f"actions are not distinct: {self.actions}")
        for key, obs in self.asked_obs.items():
            if not STATE_KEY.fullmatch(key):
                raise ValueError(f"asked_obs has a key {key[:40]!r}, not a state key")
            if len(obs) != self.obs_dim:
                raise ValueError(
                    f"asked_obs[{key}] has {len(obs)} values, but obs_dim is {self.obs_dim}"
                )
        return self


def _first_error(error: ValidationError) -> str:
    """Pydantic's first error as ``field: message, found value`` (the value cut to 60)."""
    first = error.errors()[0]
    where = ".".join(str(part) for part in first["loc"])
    message = str(first["msg"]).removeprefix("Value error, ")
    found = repr(first.get("input"))
    found = found if len(found) <= 60 else found[:57] + "..."
    head = f"{where}: " if where else ""
    return f"{head}{message}" + ("" if first["type"] == "value_error" else f", found {found}")


def check_ledger_rest(data: Mapping[str, Any], where: str) -> LedgerRest:
    """The observations, names, sizes and generator of a ledger, checked (:class:`LedgerRest`).

    Raises:
        AmuledError: One line naming ``where``, the field, what was found and ``--force``.

    """
    try:
        return LedgerRest.model_validate(dict(data))
    except ValidationError as error:
        raise AmuledError(
            f"{where}: {_first_error(error)}; the file was edited or damaged; {_START_OVER}"
        ) from None


def check_state_keys(keys: Iterable[str], field: str, where: str) -> None:
    """Refuse a ledger entry that is not a state key as a fine-tune writes it (32 hex digits).

    Raises:
        AmuledError: One line naming ``where``, ``field``, the entry and ``--force``.

    """
    for key in keys:
        if not STATE_KEY.fullmatch(key):
            raise AmuledError(
                f"{where}: {field} holds {key[:40]!r}, not a state key (32 hexadecimal "
                f"digits, as a fine-tune writes them); the file was edited; {_START_OVER}"
            )


class Example(BaseModel):
    """One line of ``distill-examples.jsonl``: a state's key, observation and beliefs.

    The lengths and the beliefs' sums are checked by the reader, which knows the task
    (:meth:`amuled_ma.distill.source.DistilledSource` through :func:`check_example`).
    """

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)

    key: str = Field(pattern=STATE_KEY.pattern)
    obs: list[_Finite] = Field(max_length=MAX_OBS_DIM)
    beliefs: dict[_Name, list[_Finite]] = Field(max_length=MAX_NAMES)


def check_example(record: object, where: str) -> Example:
    """One training pair, checked (:class:`Example`).

    Raises:
        AmuledError: One line naming ``where`` (``FILE:LINE``), the field and ``--force``.

    """
    try:
        return Example.model_validate(record)
    except ValidationError as error:
        raise AmuledError(
            f"{where}: {_first_error(error)}; the file was edited or damaged; {_START_OVER}"
        ) from None


def check_counters(
    counters: object, names: Iterable[str], asked: int, where: str
) -> dict[str, int]:
    """The ``counters`` of a state file, checked: integers in ``[0, 2**53]``, consistent.

    Args:
        counters: The file's ``counters`` table.
        names: The counters expected (:class:`~amuled_ma.distill.source.DistillStats`).
        asked: States asked (the ledger's): no more refits than that.
        where: The file, named in an error.

    Returns:
        The counters.

    Raises:
        AmuledError: A counter missing, unknown, not an integer (a string, a float, a
            bool), negative or above :data:`MAX_COUNTER`, more requests sent than
            forwarded, or more refits than asked states: one line naming the file and
            ``--force``.

    """
    names = list(names)
    fix = "the file was edited or damaged; start the fine-tune over with --force"
    if not isinstance(counters, Mapping) or set(counters) != set(names):
        raise AmuledError(f"{where}: 'counters' must hold {', '.join(names)}; {fix}")
    for name in names:
        value = counters[name]
        if type(value) is not int or not 0 <= value <= MAX_COUNTER:
            raise AmuledError(
                f"{where}: counters.{name} is {value!r}, expected an integer in "
                f"[0, {MAX_COUNTER}]; {fix}"
            )
    if counters.get("requests_sent", 0) > counters.get("requests_forwarded", 0):
        raise AmuledError(
            f"{where}: counters.requests_sent ({counters['requests_sent']}) exceeds "
            f"counters.requests_forwarded ({counters['requests_forwarded']}); {fix}"
        )
    if counters.get("refits", 0) > asked:
        raise AmuledError(
            f"{where}: counters.refits ({counters['refits']}) exceeds the {asked} states "
            f"asked; {fix}"
        )
    return {name: int(counters[name]) for name in names}


class StateFiles:
    """The two state files of one fine-tune folder.

    Args:
        folder: The fine-tune's folder (created on the first write).

    """

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)
        self.ledger = self.folder / LEDGER_FILE
        self.examples = self.folder / EXAMPLES_FILE
        self.saved_at = 0.0

    def exists(self) -> bool:
        """Whether a ledger was written."""
        return self.ledger.is_file()

    def reset(self) -> None:
        """Remove both files (a fine-tune that starts over)."""
        for path in (self.ledger, self.examples):
            path.unlink(missing_ok=True)

    def load(self) -> dict[str, Any]:
        """Read the ledger.

        Raises:
            AmuledError: It is larger than :data:`MAX_LEDGER_BYTES` (refused before it is
                read) or not readable JSON of this format; the message names the file and
                ``--force`` (start over).
            UnsafePathError: It is a link or not a regular file (nothing is read).

        """
        ledger = checked_read_path(self.folder, LEDGER_FILE)
        try:
            raw = read_bounded_bytes(
                ledger,
                MAX_LEDGER_BYTES,
                "budget state",
                note="a budget of 1,000,000 asked states is about 740 MB",
                fix=f"the file was edited or is not this run's; {_START_OVER}",
            )
            data = json.loads(raw)
        except (OSError, ValueError, RecursionError) as error:
            if isinstance(error, RecursionError):
                error = ValueError("nested deeper than Python's JSON reader can follow")
            raise AmuledError(
                f"{self.ledger}: not a readable budget state ({error}); start the fine-tune "
                "over with --force"
            ) from error
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise AmuledError(
                f"{self.ledger}: not a budget state of format {FORMAT!r}; start the "
                "fine-tune over with --force"
            )
        return data

    def save(self, data: Mapping[str, Any]) -> None:
        """Write the ledger whole or not at all, never through a link.

        Raises:
            UnsafePathError: The ledger is a link or not a regular file; nothing written.
            FileWriteError: The write failed (a full disk); the old ledger is kept.

        """
        self.folder.mkdir(parents=True, exist_ok=True)
        with atomic_writer(self.ledger, text=True) as handle:
            json.dump({"format": FORMAT, **data}, handle, separators=(",", ":"))
        self.saved_at = time.monotonic()

    def append(self, records: Iterable[Mapping[str, Any]]) -> None:
        """Append training pairs, one JSON line each, never through a link.

        Raises:
            UnsafePathError: The pairs file is a link or not a regular file.
            FileWriteError: The write failed (a full disk); the pairs before are kept.

        """
        lines = "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in records)
        if not lines:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        append_text(self.examples, lines)

    def read_examples(self) -> list[tuple[str, Example]]:
        """Every training pair written (a cut last line is skipped), with its ``FILE:LINE``.

        Raises:
            AmuledError: A line other than the last is not JSON (the file was edited) or
                not an :class:`Example` (a key, finite numbers, nothing else), the file is
                larger than :data:`MAX_EXAMPLES_BYTES` or a line longer than
                :data:`MAX_EXAMPLE_LINE_BYTES` (refused before it is read whole).
            UnsafePathError: It is a link or not a regular file (nothing is read).

        """
        if not checked_read_path(self.folder, EXAMPLES_FILE).is_file():
            return []
        fix = f"the file was edited or is not this run's; {_START_OVER}"
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
                            f"{self.examples}:{number}: not JSON ({error}); {_START_OVER}"
                        ) from None
                    where = f"{self.examples}:{number}"
                    out.append((where, check_example(record, where)))
        except OSError as error:
            raise AmuledError(
                f"{self.examples}: cannot read the training pairs ({error}); {_START_OVER}"
            ) from error
        return out
