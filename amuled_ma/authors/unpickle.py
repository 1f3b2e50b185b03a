"""Read the authors' LLM-cache pickles without running code from them (docs/authors.md).

`scan_pickle` first refuses a file naming a global outside `ALLOWED_GLOBALS` or nested deeper
than `MAX_DEPTH`, nothing built; then `BoundedReader` builds the values within the bounds below.
"""

from __future__ import annotations

import math
import os
import pickle
import pickletools
import resource
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn, TypeVar, cast

import numpy as np

from amuled_ma.errors import AuthorsImportError, UnsafePickleError

#: Most memory the values of one file may take [bytes per byte of the file, plus
#: `MEMORY_SLACK_BYTES`]: the 1.95 MB cache takes about 57 MB (29 per byte).
MEMORY_PER_BYTE = 64
#: Memory allowed on top of `MEMORY_PER_BYTE` times the file's size [bytes].
MEMORY_SLACK_BYTES = 64 * 2**20
#: Opcodes between two looks at the process's resident memory (and at the opcode budget).
MEMORY_CHECK_EVERY = 2**15
#: Most opcodes read from one file: reading costs time per opcode (about 1.5 us), and 16 MiB
#: of one-byte opcodes took 28-39 s; 2.3 times the published caches' most (896,093).
MAX_OPCODES = 2**21
#: Most entries of one array (the authors' arrays hold one value per action).
MAX_ARRAY_ITEMS = 2**20
#: Most keys of one dict or set sharing one hash value: dicts insert those in quadratic time
#: (a 2 MB file of colliding integer keys took over 13 minutes); the caches have none.
MAX_EQUAL_HASHES = 8
#: Most work hashing dict keys and set items, all together [units: one a key, plus one a
#: value of a tuple or frozenset key]: an opcode may hash 65 values (a memoized 64-value
#: tuple reused), so the opcode cap alone let a file spend minutes on keys; 7.1 times the
#: published caches' most (147,488).
MAX_KEY_WORK = 2**20
#: Most items of a tuple or frozenset key (the caches' keys are observations of 8 or 11).
MAX_KEY_ITEMS = 64
#: Largest integer (absolute) in a key: below ``sys.hash_info.modulus``, integers hash to
#: themselves (the caches' keys hold none).
MAX_KEY_INT = 2**61 - 2
#: numpy dtype kinds a cache may hold: bool, signed and unsigned integers, floats, complex
#: numbers. Void (``V``), object (``O``), structured, string and datetime dtypes are refused.
ALLOWED_DTYPE_KINDS = frozenset("biufc")
#: ``(module, name)`` of every global a cache may name, both numpy spellings
#: (``numpy.core`` before numpy 2, ``numpy._core`` since), plus the builtin sets that
#: pickle protocols below 4 name instead of using their opcodes. These are names in the
#: file only: each resolves to a checked function of the reader, never to numpy's own.
ALLOWED_GLOBALS: frozenset[tuple[str, str]] = frozenset(
    {
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("builtins", "frozenset"),
        ("builtins", "set"),
    }
)
#: Opcodes whose decoded argument is the value they push.
_VALUES = frozenset(
    {
        "INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4", "FLOAT", "BINFLOAT",
        "UNICODE", "SHORT_BINUNICODE", "BINUNICODE", "BINUNICODE8",
        "SHORT_BINBYTES", "BINBYTES", "BINBYTES8",
    }
)  # fmt: skip
#: Opcodes that instantiate arbitrary classes: refused with their own line.
_OBJECTS = frozenset({"OBJ", "INST", "NEWOBJ", "NEWOBJ_EX"})
#: Opcodes that push a constant or a new empty container: what makes it.
_NEW: dict[str, Callable[[], object]] = {
    "NONE": lambda: None,
    "NEWTRUE": lambda: True,
    "NEWFALSE": bool,
    "EMPTY_TUPLE": tuple,
    "EMPTY_LIST": list,
    "EMPTY_DICT": dict,
    "EMPTY_SET": set,
}
_Items = TypeVar("_Items", bound=Collection[Any])


class PickleRefused(Exception):
    """A global, opcode or numpy value outside the allow-list."""


class PickleUnbounded(Exception):
    """A value that would cost unbounded time or memory."""


@dataclass(frozen=True, slots=True)
class _Allowed:
    """What an allowed global resolves to: a checked function, callable by ``REDUCE`` only."""

    name: str
    call: Callable[..., Any]


def _ndarray(*_args: object) -> NoReturn:
    raise PickleRefused("numpy.ndarray called directly (only allowed through _reconstruct)")


def _checked_dtype(dtype: object) -> np.dtype:
    """``dtype`` if it is a plain numeric dtype (`ALLOWED_DTYPE_KINDS`), else refuse."""
    if not isinstance(dtype, np.dtype):
        raise PickleRefused(f"a dtype that is not a numpy dtype ({type(dtype).__name__})")
    if (
        dtype.hasobject
        or dtype.kind not in ALLOWED_DTYPE_KINDS
        or dtype.fields is not None
        or dtype.subdtype is not None
        or dtype.itemsize > 16
    ):
        what = "object" if dtype.hasobject else "void" if dtype.kind == "V" else "non-numeric"
        raise PickleRefused(
            f"{what} dtype {dtype!r} (only bool, integer, float and complex numbers are "
            "allowed; object, void and structured dtypes are refused)"
        )
    return dtype


def _check_dtype_state(state: object) -> None:
    """A numeric dtype's state: ``(3, byte order, None, None, None, -1, -1, 0)``."""
    if not (
        isinstance(state, tuple)
        and len(state) == 8
        and state[0] == 3
        and state[1] in ("<", ">", "|", "=")
        and state[2:5] == (None, None, None)
        and state[5:] == (-1, -1, 0)
    ):
        raise PickleRefused(f"a dtype state {short_repr(state)} (only plain numeric dtypes)")


def _shape(shape: object) -> tuple[int, ...]:
    if not (
        isinstance(shape, tuple)
        and len(shape) <= 32
        and all(type(n) is int and 0 <= n <= MAX_ARRAY_ITEMS for n in shape)
    ):
        raise PickleRefused(f"array of shape {short_repr(shape)}")
    if math.prod(shape) > MAX_ARRAY_ITEMS:
        raise PickleRefused(f"array of shape {shape!r} (more than {MAX_ARRAY_ITEMS:,} entries)")
    return shape


def _check_key(key: object) -> None:
    """Refuse a dict key or set item whose hashing could cost more than a flat observation's."""
    kind = type(key)
    if kind is str or kind is bytes or kind is float or kind is bool or key is None:
        return
    if type(key) is int:
        if -MAX_KEY_INT <= key <= MAX_KEY_INT:
            return
        raise PickleUnbounded(
            f"an integer dict key or set item of {key.bit_length()} bits, beyond +-(2**61 - 2) "
            "(multiples of 2**61 - 1 all hash alike)"
        )
    if isinstance(key, np.generic):
        return  # built by _scalar: a number of an allowed dtype
    if type(key) is tuple or type(key) is frozenset:
        if len(key) > MAX_KEY_ITEMS:
            raise PickleUnbounded(
                f"a dict key or set item of {len(key):,} values (at most {MAX_KEY_ITEMS})"
            )
        for item in key:
            if type(item) in (tuple, frozenset):
                raise PickleUnbounded("a dict key or set item nested in another (keys are flat)")
            _check_key(item)
        return
    raise PickleRefused(
        f"a dict key or set item of type {kind.__name__} (keys are strings, numbers, and flat "
        "tuples or frozensets of them)"
    )


class BoundedReader:
    """Builds one pickle's values, opcode by opcode, with the allow-list and the bounds.

    ``max_array_bytes``: most bytes of all arrays, and most items ``set()``/``frozenset()``
    calls may hash, all together; ``max_memory``: most bytes resident memory may grow by
    (None: no limit), looked at every `MEMORY_CHECK_EVERY` opcodes.
    """

    def __init__(
        self,
        data: bytes,
        *,
        max_array_bytes: int,
        max_memory: int | None,
        max_opcodes: int = MAX_OPCODES,
        max_key_work: int = MAX_KEY_WORK,
    ) -> None:
        self.data = data
        self.max_key_work = self.key_work_left = max_key_work
        self.max_opcodes = max_opcodes
        self.array_bytes_left = max_array_bytes
        self.set_items_left = max_array_bytes
        self.max_memory = max_memory
        self.stack: list[Any] = []
        self.metastack: list[list[Any]] = []
        self.memo: dict[int, Any] = {}
        # id of a dict or set -> (it, kept so that its id is not reused; its keys by hash)
        self.counters: dict[int, tuple[object, dict[int, int]]] = {}
        self.ndarray = _Allowed("numpy.ndarray", _ndarray)
        self.targets = {
            "scalar": _Allowed("numpy scalar", self._scalar),
            "_reconstruct": _Allowed("numpy _reconstruct", self._reconstruct),
            "ndarray": self.ndarray,
            "dtype": _Allowed("numpy.dtype", self._dtype),
            "frozenset": _Allowed("frozenset", self._frozenset),
            "set": _Allowed("set", self._set),
        }
        push = self._push
        self.handlers: dict[str, Callable[[Any], object]] = {
            "PROTO": self._proto,
            "FRAME": lambda _: None,  # framing only groups opcodes; genops reads through it
            "MARK": self._mark,
            "POP": self._pop,
            "POP_MARK": lambda _: self._pop_mark(),
            "DUP": lambda _: push(self.stack[-1]),
            "MEMOIZE": self._memoize,
            # the items above a mark are popped before `push` reads self.stack again
            "TUPLE": lambda _: push(tuple(self._pop_mark())),
            "TUPLE1": lambda _: push(tuple(self._pop_top(1))),
            "TUPLE2": lambda _: push(tuple(self._pop_top(2))),
            "TUPLE3": lambda _: push(tuple(self._pop_top(3))),
            "LIST": lambda _: push(self._pop_mark()),
            "APPEND": lambda _: self._into_list("APPEND", self._pop_top(1)),
            "APPENDS": lambda _: self._into_list("APPENDS", self._pop_mark()),
            "DICT": lambda _: push(self._into_dict(self._pop_mark(), {})),
            "SETITEM": lambda _: self._into_dict(self._pop_top(2)),
            "SETITEMS": lambda _: self._into_dict(self._pop_mark()),
            "ADDITEMS": lambda _: self._into_set(self._pop_mark()),
            "FROZENSET": lambda _: push(frozenset(self._admitted(self._pop_mark()))),
            "GLOBAL": self._global,
            "STACK_GLOBAL": self._stack_global,
            "REDUCE": self._reduce,
            "BUILD": self._build,
        }
        for name in ("PUT", "BINPUT", "LONG_BINPUT"):
            self.handlers[name] = self._put
        for name in ("GET", "BINGET", "LONG_BINGET"):
            self.handlers[name] = lambda arg: push(self.memo[arg])

    def read(self) -> Any:
        """The pickle's value.

        Raises:
            PickleRefused: Something outside the allow-list.
            PickleUnbounded: Something that would take unbounded time or memory.
            ValueError: A malformed pickle (``IndexError``, ``KeyError`` too).
        """
        handlers = self.handlers
        start = _resident_bytes() if self.max_memory is not None else 0
        for read, (op, arg, _pos) in enumerate(pickletools.genops(self.data), 1):
            name = op.name
            if name in _VALUES:
                self.stack.append(arg)
            elif name in _NEW:
                self.stack.append(_NEW[name]())
            elif name == "STOP":
                return self.stack.pop()
            else:
                handler = handlers.get(name)
                if handler is None:
                    raise PickleRefused(
                        "an object built by OBJ, INST or NEWOBJ (caches need none)"
                        if name in _OBJECTS
                        else f"the opcode {name} (caches need none)"
                    )
                handler(arg)
            if read % MEMORY_CHECK_EVERY == 0:
                if read > self.max_opcodes:
                    raise PickleUnbounded(too_many_opcodes(self.max_opcodes))
                self._check_memory(start)
        raise ValueError("pickle exhausted before seeing STOP")

    def _check_memory(self, start: int) -> None:
        if self.max_memory is not None and _resident_bytes() - start > self.max_memory:
            raise PickleUnbounded(
                f"its values take more than {self.max_memory // 2**20:,} MiB of memory "
                f"({MEMORY_PER_BYTE} bytes per byte of the file, plus "
                f"{MEMORY_SLACK_BYTES // 2**20} MiB)"
            )

    def _proto(self, arg: int) -> None:
        if not 0 <= arg <= pickle.HIGHEST_PROTOCOL:
            raise ValueError(f"unsupported pickle protocol: {arg}")

    def _mark(self, _arg: None) -> None:
        self.metastack.append(self.stack)
        self.stack = []

    def _pop_mark(self) -> list[Any]:
        items = self.stack
        self.stack = self.metastack.pop()
        return items

    def _pop(self, _arg: None) -> None:
        if self.stack:
            self.stack.pop()
        else:
            self._pop_mark()

    def _put(self, arg: int) -> None:
        if arg < 0:
            raise ValueError("negative PUT argument")
        self.memo[arg] = self.stack[-1]

    def _memoize(self, _arg: None) -> None:
        self.memo[len(self.memo)] = self.stack[-1]

    def _push(self, value: object) -> None:
        self.stack.append(value)

    def _pop_top(self, n: int) -> list[Any]:
        stack = self.stack
        if len(stack) < n:
            raise IndexError("stack underflow")
        items = stack[-n:]
        del stack[-n:]
        return items

    def _into_list(self, opcode: str, items: list[Any]) -> None:
        target = self.stack[-1]
        if type(target) is not list:
            raise PickleRefused(f"{opcode} on a {type(target).__name__}")
        target.extend(items)

    def _admit(self, counts: dict[int, int], key: object) -> None:
        """Check a dict key or set item, spend its key work, count its hash in ``counts``."""
        _check_key(key)
        self.key_work_left -= 1 + len(key) if type(key) is tuple or type(key) is frozenset else 1
        if self.key_work_left < 0:
            raise PickleUnbounded(
                f"more than {self.max_key_work:,} units of work hashing dict keys and set items "
                "(one a key and one a value of a tuple key; the published caches need at most "
                "147,488)"
            )
        h = hash(key)
        n = counts.get(h, 0) + 1
        if n > MAX_EQUAL_HASHES:
            raise PickleUnbounded(
                f"more than {MAX_EQUAL_HASHES} keys of one dict or set share one hash value "
                "(keys crafted to collide make reading take quadratic time)"
            )
        counts[h] = n

    def _counts(self, container: object) -> dict[int, int]:
        """The hash counts of one dict or set, kept while the file is read."""
        entry = self.counters.get(id(container))
        if entry is None or entry[0] is not container:
            entry = self.counters[id(container)] = (container, {})
        return entry[1]

    def _into_dict(self, items: list[Any], target: object = None) -> object:
        """Add ``items`` (key, value, ...) to ``target`` (None: the dict on top of the stack)."""
        target = self.stack[-1] if target is None else target
        if type(target) is not dict:
            raise PickleRefused(f"SETITEM on a {type(target).__name__}")
        if len(items) % 2:
            raise ValueError("odd number of items for a dict")
        counts = self._counts(target)
        for i in range(0, len(items), 2):
            self._admit(counts, items[i])
            target[items[i]] = items[i + 1]
        return target

    def _into_set(self, items: Collection[Any], target: object = None) -> None:
        """Add ``items`` to ``target`` (None: the set on top of the stack)."""
        target = self.stack[-1] if target is None else target
        if type(target) is not set:
            raise PickleRefused(f"ADDITEMS on a {type(target).__name__}")
        counts = self._counts(target)
        for item in items:
            self._admit(counts, item)
            target.add(item)

    def _admitted(self, items: _Items) -> _Items:
        counts: dict[int, int] = {}
        for item in items:
            self._admit(counts, item)
        return items

    def _find(self, module: str, name: str) -> _Allowed:
        if (module, name) not in ALLOWED_GLOBALS:
            raise PickleRefused(f"global {module}.{name} is not allowed")
        return self.targets[name]

    def _global(self, arg: str) -> None:
        module, name = arg.split(" ", 1)  # genops joins GLOBAL's two lines with a space
        self.stack.append(self._find(module, name))

    def _stack_global(self, _arg: None) -> None:
        name = self.stack.pop()
        module = self.stack.pop()
        if type(name) is not str or type(module) is not str:
            raise ValueError("STACK_GLOBAL requires str")
        self.stack.append(self._find(module, name))

    def _reduce(self, _arg: None) -> None:
        stack = self.stack
        args = stack.pop()
        func = stack[-1]
        if type(func) is not _Allowed:
            raise PickleRefused(f"REDUCE on a {type(func).__name__} (only allowed globals)")
        if type(args) is not tuple:
            raise PickleRefused(f"{func.name} called on a {type(args).__name__}, not a tuple")
        stack[-1] = func.call(*args)

    def _spend(self, nbytes: int, what: str) -> None:
        if nbytes > self.array_bytes_left:
            raise PickleUnbounded(
                f"{what} of {nbytes:,} bytes, more than the file's size allows (arrays hold "
                "at most as many bytes as the file has)"
            )
        self.array_bytes_left -= nbytes

    def _scalar(self, dtype: object, *args: object) -> np.generic:
        checked = _checked_dtype(dtype)
        data = args[0] if len(args) == 1 else None
        if type(data) is not bytes or len(data) != checked.itemsize:
            raise PickleRefused(f"numpy scalar of dtype {checked!r} not built from its bytes")
        return np.frombuffer(data, dtype=checked)[0]

    def _reconstruct(self, subtype: object, shape: object, dtype: object) -> np.ndarray:
        if subtype is not self.ndarray:
            raise PickleRefused("_reconstruct of anything but numpy.ndarray")
        dims = _shape(shape)
        if type(dtype) is bytes and len(dtype) <= 8:
            dtype = np.dtype(dtype.decode("ascii"))
        checked = _checked_dtype(dtype)
        self._spend(math.prod(dims) * checked.itemsize, f"array of shape {dims}")
        return np.zeros(dims, checked)  # its values come from BUILD

    def _dtype(self, spec: object, align: object = False, copy: object = True) -> np.dtype:
        if type(spec) is not str or len(spec) > 8 or align is not False:
            raise PickleRefused(f"dtype({spec!r}, {align!r}) (only plain numeric type codes)")
        try:
            dtype = np.dtype(spec)
        except TypeError as error:
            raise PickleRefused(f"dtype {spec!r} ({error})") from error
        _checked_dtype(dtype)
        return np.dtype(spec, align=False, copy=True)  # a copy: BUILD never alters numpy's own

    def _frozenset(self, items: object = ()) -> frozenset[Any]:
        return frozenset(self._admitted(self._set_items(items)))

    def _set(self, items: object = ()) -> set[Any]:
        result: set[Any] = set()
        self._into_set(self._set_items(items), result)  # ADDITEMS on it goes on counting
        return result

    def _set_items(self, items: object) -> Collection[Any]:
        # type(...) refuses subclasses; isinstance tells the type checker what passed
        if type(items) not in (list, tuple, set, frozenset) or not isinstance(
            items, list | tuple | set | frozenset
        ):
            raise PickleRefused(f"a set of a {type(items).__name__} (only of a list or tuple)")
        if len(items) > self.set_items_left:
            raise PickleUnbounded(
                "set() and frozenset() calls on more items, all together, than the file has bytes"
            )
        self.set_items_left -= len(items)
        return items

    def _build(self, _arg: None) -> None:
        """``BUILD``: only an array's or a dtype's state, checked before it is set."""
        state = self.stack.pop()
        inst = self.stack[-1]
        if type(inst) is np.ndarray:
            self._check_array_state(state)
        elif isinstance(inst, np.dtype):
            _check_dtype_state(state)
        else:
            raise PickleRefused(f"BUILD of a {type(inst).__name__} (only arrays and dtypes)")
        inst.__setstate__(state)
        if isinstance(inst, np.dtype):
            _checked_dtype(inst)

    def _check_array_state(self, state: object) -> None:
        if not (isinstance(state, tuple) and len(state) == 5 and state[0] == 1):
            raise PickleRefused("an array state that is not (1, shape, dtype, fortran, bytes)")
        _, shape, dtype, fortran, data = state
        shape = _shape(shape)
        dtype = _checked_dtype(dtype)
        nbytes = math.prod(shape) * dtype.itemsize
        if type(fortran) is not bool or type(data) is not bytes or len(data) != nbytes:
            raise PickleRefused(
                f"an array state of shape {shape} and dtype {dtype} without its "
                f"{nbytes:,} bytes of data"
            )
        self._spend(nbytes, f"array of shape {shape}")


def too_many_opcodes(limit: int) -> str:
    """The refusal of a file of more than ``limit`` opcodes (its time is per opcode)."""
    return (
        f"more than {limit:,} opcodes (the published caches have at most 896,093; reading "
        "takes time per opcode, so a longer file would take minutes)"
    )


def _resident_bytes() -> int:
    """The process's resident memory now (Linux ``/proc/self/statm``), else its peak."""
    try:
        with open("/proc/self/statm", "rb") as handle:
            return int(handle.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def short_repr(value: object) -> str:
    """``repr(value)``, cut to 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


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
