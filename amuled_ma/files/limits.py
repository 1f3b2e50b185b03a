"""Size caps on files read whole, refused from their size before a byte is read (``docs/trust.md``).

A file whose size is not reported is cut at the cap + 1 byte; JSON Lines cap each line
(`read_line`).
"""

from __future__ import annotations

import json
import os
from typing import IO, Any, AnyStr

from amuled_ma.errors import AmuledError

#: The usual fix in a refusal: most over-large inputs are the wrong file.
RIGHT_FILE = "is it the right file?"


def _a(noun: str) -> str:
    """``noun`` with its indefinite article (``"a checkpoint"``, ``"an export line"``)."""
    return f"{'an' if noun[:1].lower() in 'aeiou' else 'a'} {noun}"


def too_large(head: str, size: int, limit: int, noun: str, *, note: str = "", fix: str) -> str:
    """The one-line refusal of a file over its cap.

    ``"HEAD is SIZE bytes, more than the LIMIT a NOUN may be (NOTE); it is not read; FIX"``,
    ``HEAD`` e.g. ``"runs/x/config.json: the run record"``, `` (NOTE)`` only when given.
    """
    why = f" ({note})" if note else ""
    return (
        f"{head} is {size:,} bytes, more than the {limit:,} {_a(noun)} may be{why}; "
        f"it is not read; {fix}"
    )


def check_size(
    path: str | os.PathLike[str],
    limit: int,
    noun: str,
    *,
    error: type[Exception] = AmuledError,
    head: str | None = None,
    note: str = "",
    fix: str = RIGHT_FILE,
) -> int:
    """Refuse a file larger than ``limit`` bytes from its size, before a byte is read.

    For files handed whole to another reader (``torch.load``); read the file with
    :func:`read_bounded_bytes` where we read it ourselves.

    ``error`` (an :class:`~amuled_ma.errors.AmuledError` subclass) is raised with the line of
    :func:`too_large`, ``head`` defaulting to ``"PATH: the NOUN"`` (``noun`` e.g.
    ``"checkpoint"``). Returns the file's size in bytes.

    Raises:
        OSError: The file cannot be examined (the caller words that).
    """
    size = os.stat(path).st_size
    if size > limit:
        head = f"{path}: the {noun}" if head is None else head
        raise error(too_large(head, size, limit, noun, note=note, fix=fix))
    return size


def read_bounded_bytes(
    path: str | os.PathLike[str],
    limit: int,
    noun: str,
    *,
    error: type[Exception] = AmuledError,
    head: str | None = None,
    note: str = "",
    fix: str = RIGHT_FILE,
) -> bytes:
    """A file's bytes, refused when it holds more than ``limit`` (never read past the cap).

    The size is checked on the open file; a file that reports less than it holds (``/proc``,
    a file written to meanwhile) is read up to ``limit + 1`` bytes and refused the same way.
    Arguments and errors as :func:`check_size`.
    """
    head = f"{path}: the {noun}" if head is None else head
    with open(path, "rb") as handle:
        size = os.fstat(handle.fileno()).st_size
        if size > limit:
            raise error(too_large(head, size, limit, noun, note=note, fix=fix))
        data = handle.read(limit + 1)
    if len(data) > limit:
        why = f" ({note})" if note else ""
        raise error(
            f"{head} holds more than the {limit:,} bytes {_a(noun)} may be{why}; it is not "
            f"read; {fix}"
        )
    return data


def read_bounded_text(
    path: str | os.PathLike[str],
    limit: int,
    noun: str,
    *,
    error: type[Exception] = AmuledError,
    note: str = "",
    fix: str = RIGHT_FILE,
) -> str:
    """A UTF-8 text file (:func:`decode_text`), refused when over ``limit`` bytes or unreadable.

    Arguments as :func:`check_size`; every refusal is ``error``, one line naming the file,
    the problem and the fix.
    """
    try:
        data = read_bounded_bytes(path, limit, noun, error=error, note=note, fix=fix)
    except OSError as failure:
        if isinstance(failure, error):  # the refusal itself (an error class that is an OSError)
            raise
        raise error(
            f"{path}: cannot read the {noun}: {failure.strerror or failure}; check the path"
        ) from failure
    return decode_text(path, data, noun, error=error)


def decode_text(
    path: str | os.PathLike[str], data: bytes, noun: str, *, error: type[Exception] = AmuledError
) -> str:
    """``data`` read from ``path`` as UTF-8 text, newlines as ``Path.read_text`` reads them.

    Not UTF-8 text is ``error``, one line naming the file and the byte.
    """
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as failure:
        raise error(
            f"{path}: the {noun} is not UTF-8 text ({failure.reason} at byte {failure.start}); "
            "save it as UTF-8"
        ) from failure
    return text.replace("\r\n", "\n").replace("\r", "\n")  # CR LF and a lone CR -> LF


def read_bounded_json(
    path: str | os.PathLike[str],
    limit: int,
    noun: str,
    *,
    note: str = "",
    fix: str = RIGHT_FILE,
) -> Any:
    """A JSON file read whole, refused with one line when over ``limit``, unreadable or not JSON.

    Arguments as :func:`check_size` (``fix`` ends every message).

    Raises:
        AmuledError: ``"PATH: ... FIX"``: the file is over ``limit`` bytes (refused from its
            size, before it is read), cannot be read (``cannot read it``) or is not JSON
            (``not JSON``: malformed, not UTF-8, nested deeper than Python can follow).
    """
    try:
        return json.loads(read_bounded_bytes(path, limit, noun, note=note, fix=fix))
    except OSError as err:
        raise AmuledError(f"{path}: cannot read it ({err.strerror or err}); {fix}") from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise AmuledError(f"{path}: not JSON ({err}); {fix}") from None


def read_line(
    handle: IO[AnyStr],
    limit: int,
    where: str,
    *,
    error: type[Exception] = AmuledError,
    unit: str = "characters",
    fix: str,
) -> AnyStr:
    """The next line of ``handle`` with its newline ("" at the end), refused when longer.

    ``limit`` counts characters (text) or bytes (binary, ``unit="bytes"``), the newline
    not counted; a longer line is ``error``: ``"WHERE: a line longer than the N characters a
    line may be ...; FIX"``, ``where`` being ``FILE:LINE``.
    """
    line = handle.readline(limit + 1)
    if len(line) > limit and not (len(line) == limit + 1 and line[-1:] in ("\n", b"\n")):
        raise error(
            f"{where}: a line longer than the {limit:,} {unit} a line may be (it is not read "
            f"whole); {fix}"
        )
    return line
