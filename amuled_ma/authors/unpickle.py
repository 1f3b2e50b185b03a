"""Read the authors' LLM-cache pickles without running code from them.

A pickle is a program: ``pickle.load`` calls whatever global the file names. `load_pickle`
first scans the opcodes (`scan_pickle`, nothing built) and refuses a file naming a global
outside `ALLOWED_GLOBALS`, or nested deeper than `MAX_DEPTH` (deep tuples crash CPython's
unpickler); then `BoundedReader` builds the values within the bounds of
`amuled_ma.authors.pickle_reader` (tabled in docs/authors.md).
"""

from __future__ import annotations

import pickletools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from amuled_ma.authors.pickle_reader import (
    ALLOWED_GLOBALS,
    MAX_OPCODES,
    MEMORY_PER_BYTE,
    MEMORY_SLACK_BYTES,
    BoundedReader,
    PickleRefused,
    PickleUnbounded,
    too_many_opcodes,
)
from amuled_ma.errors import AuthorsImportError, UnsafePickleError

#: Largest pickle read [bytes]: 8 times the largest published cache (1.95 MB, Driving
#: llama-3.1-70B, read in about 4 s); reading is linear in the file's size.
MAX_PICKLE_BYTES = 16 * 2**20
#: Deepest nesting of values accepted (the authors' caches nest 9 deep, counting each
#: opcode that wraps values: dict, key tuple, numpy scalar, its arguments, ...).
MAX_DEPTH = 64
#: The first bytes of a Git LFS pointer file (a checkout made without ``git lfs pull``).
_LFS_POINTER = b"version https://git-lfs"


#: Opcodes that add values to the container below them on the stack (which keeps its depth).
_MODIFY = frozenset({"APPEND", "APPENDS", "SETITEM", "SETITEMS", "ADDITEMS", "BUILD"})
_PUT, _MEMOIZE, _GET, _MARK, _PUSH, _NOTHING, _OTHER = range(7)
_MEMO_KINDS = {"PUT": _PUT, "BINPUT": _PUT, "LONG_BINPUT": _PUT, "MEMOIZE": _MEMOIZE, "MARK": _MARK}
_MEMO_KINDS |= {"GET": _GET, "BINGET": _GET, "LONG_BINGET": _GET}


def _opcode_table() -> dict[str, tuple[int, bool, int, int, bool]]:
    """Per opcode: ``(kind, pops to a mark, fixed items popped, items pushed, modifies)``."""
    mark = pickletools.markobject
    table = {}
    for op in pickletools.opcodes:
        before, after = op.stack_before, op.stack_after
        if op.name in _MEMO_KINDS:
            kind = _MEMO_KINDS[op.name]
        elif not before and len(after) == 1 and not op.name.startswith(("EXT", "PERSID")):
            kind = _PUSH
        elif not before and not after:
            kind = _NOTHING  # PROTO, FRAME
        else:
            kind = _OTHER
        fixed = before.index(mark) if mark in before else len(before)
        table[op.name] = (kind, mark in before, fixed, len(after), op.name in _MODIFY)
    return table


_OPCODES = _opcode_table()


def _depth(item: object) -> int:
    return item if type(item) is int else 1  # a string pushed by the file


@dataclass
class PickleScan:
    """What a pickle holds, from its opcodes alone: globals named (in order), depth, opcodes."""

    globals: list[str]
    depth: int
    opcodes: int = 0


def scan_pickle(
    data: bytes, *, max_depth: int = MAX_DEPTH, max_opcodes: int = MAX_OPCODES
) -> PickleScan:
    """Read a pickle's opcodes (nothing built; stops past ``max_depth``, ``max_opcodes``).

    The stack holds each entry's depth, or a pushed string for ``STACK_GLOBAL``.

    Raises:
        ValueError: The bytes are not a well-formed pickle.
    """
    stack: list[Any] = []
    marks: list[int] = []
    memo: dict[int, Any] = {}
    found: list[str] = []
    deepest = count = 0
    try:
        for op, arg, _pos in pickletools.genops(data):
            count += 1
            if count > max_opcodes:
                break
            kind, to_mark, fixed, pushed, modifies = _OPCODES[op.name]
            if kind == _PUSH:
                stack.append(arg if type(arg) is str else 1)
            elif kind == _PUT:  # the PUT and GET opcodes' argument is the memo index
                memo[cast(int, arg)] = stack[-1]
            elif kind == _GET:
                stack.append(memo[cast(int, arg)])
            elif kind == _MEMOIZE:
                memo[len(memo)] = stack[-1]
            elif kind == _MARK:
                marks.append(len(stack))
            if kind != _OTHER:  # _NOTHING too: PROTO, FRAME
                continue
            items: list[Any] = []
            if to_mark:
                start = marks.pop()
                items = stack[start:]
                del stack[start:]
            top: list[Any] = []
            if fixed:
                if len(stack) < fixed:
                    raise IndexError("stack underflow")
                top = stack[-fixed:]
                del stack[-fixed:]
            name = op.name
            if name in ("GLOBAL", "INST"):
                found.append(str(arg).replace(" ", "."))
            elif name == "STACK_GLOBAL":
                module, attr = (x if type(x) is str else "?" for x in top)
                found.append(f"{module}.{attr}")
            elif name.startswith("EXT"):
                found.append(f"copyreg extension {arg}")
            elif "PERSID" in name:
                found.append("persistent id")
            if modifies:
                inner = max(map(_depth, items + top[1:]), default=0)
                depth = max(_depth(top[0]), 1 + inner)
            else:
                depth = 1 + max(map(_depth, items + top), default=0)
            deepest = max(deepest, depth)
            if deepest > max_depth:
                break
            stack.extend([depth] * pushed)
    except (IndexError, KeyError) as error:
        raise ValueError(f"malformed pickle ({type(error).__name__})") from error
    return PickleScan(globals=found, depth=deepest, opcodes=count)


def load_pickle(path: str | Path, *, max_bytes: int = MAX_PICKLE_BYTES) -> Any:
    """Load a pickle that may only hold numpy arrays/scalars in builtin containers.

    Raises:
        UnsafePickleError: The file names a global outside `ALLOWED_GLOBALS` (all named);
            nothing from it ran.
        AuthorsImportError: Missing, too large, a Git LFS pointer, or not a readable pickle.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as error:
        raise AuthorsImportError(f"{path}: cannot read the pickle: {error.strerror}") from error
    if size > max_bytes:
        raise AuthorsImportError(
            f"{path}: {size:,} bytes, more than the {max_bytes:,} accepted for an LLM cache; "
            "is it the authors' file?"
        )
    data = path.read_bytes()
    if data.startswith(_LFS_POINTER):
        raise AuthorsImportError(
            f"{path}: a Git LFS pointer, not the pickle; fetch the file ('git lfs pull' in "
            "the checkout) and import again"
        )
    try:
        scan = scan_pickle(data)
    except ValueError as error:
        raise AuthorsImportError(
            f"{path}: not a readable pickle ({error}); is the file complete?"
        ) from error
    refused = [g for g in scan.globals if tuple(g.rsplit(".", 1)) not in ALLOWED_GLOBALS]
    if refused:
        raise UnsafePickleError(
            f"{path}: refusing to unpickle: it names {', '.join(refused)}, which could run "
            "code (allowed: numpy arrays and scalars in tuples, dicts and sets); nothing "
            "from the file was run. Use the authors' published files, or delete this one"
        )
    if scan.opcodes > MAX_OPCODES:
        raise AuthorsImportError(
            f"{path}: refusing to unpickle: {too_many_opcodes(MAX_OPCODES)}; is it the "
            "authors' file? Nothing from the file was run"
        )
    if scan.depth > MAX_DEPTH:
        raise AuthorsImportError(
            f"{path}: refusing to unpickle: its values nest more than {MAX_DEPTH} deep (an "
            "LLM cache nests about 9; deeper nesting can crash the reader); nothing from the "
            "file was run"
        )
    try:
        return BoundedReader(
            data,
            max_array_bytes=len(data),
            max_memory=MEMORY_PER_BYTE * len(data) + MEMORY_SLACK_BYTES,
            max_opcodes=MAX_OPCODES,
        ).read()
    except PickleUnbounded as error:
        raise AuthorsImportError(
            f"{path}: refusing to unpickle: {error}; is it the authors' file? Nothing from "
            "the file was run"
        ) from error
    except PickleRefused as error:
        raise UnsafePickleError(
            f"{path}: refusing to unpickle: {error}; nothing outside the allow-list was run"
        ) from error
    except (RecursionError, MemoryError) as error:
        raise AuthorsImportError(
            f"{path}: not a readable LLM cache ({type(error).__name__} while unpickling)"
        ) from error
    except Exception as error:  # a damaged pickle raises many types
        raise AuthorsImportError(
            f"{path}: not a readable pickle ({type(error).__name__}: {error}); is the file "
            "complete?"
        ) from error
