"""Size caps on files read whole, refused from their size before a byte is read (docs/trust.md)."""

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
    """``"HEAD is SIZE bytes, more than the LIMIT a NOUN may be (NOTE); it is not read; FIX"``."""
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
    """The file's size; ``error`` (:func:`too_large`'s line) over ``limit`` bytes, before a read.

    For files handed whole to another reader (``torch.load``); ``head`` defaults to
    ``"PATH: the NOUN"``. An OSError when the file cannot be examined.
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
    """A file's bytes, refused (as :func:`check_size`) over ``limit``, never read past the cap.

    A file that reports less than it holds (``/proc``) is read up to ``limit + 1`` bytes.
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


def decode_text(
    path: str | os.PathLike[str], data: bytes, noun: str, *, error: type[Exception] = AmuledError
) -> str:
    """``data`` of ``path`` as UTF-8 text, newlines as ``Path.read_text``'s; else ``error``."""
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
    """A JSON file read whole; AmuledError (ending ``fix``) over ``limit``, unreadable, not JSON."""
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
    """The next line of ``handle`` ("" at the end); ``error`` at ``where`` over ``limit`` ``unit``.

    The newline is not counted; ``where`` is ``FILE:LINE``.
    """
    line = handle.readline(limit + 1)
    if len(line) > limit and not (len(line) == limit + 1 and line[-1:] in ("\n", b"\n")):
        raise error(
            f"{where}: a line longer than the {limit:,} {unit} a line may be (it is not read "
            f"whole); {fix}"
        )
    return line
