"""Read the authors' LLM-cache pickles without running code from them.

A pickle is a program: ``pickle.load`` calls whatever global the file names (``os.system``,
say) with arguments from the file. The authors' caches only need numpy arrays and scalars
inside builtin containers (tuples, dicts and frozensets come from pickle's own opcodes),
so :func:`load_pickle` allows exactly these globals, :data:`ALLOWED_GLOBALS`, and refuses
a file that names any other one:

1. a *scan* of the file's opcodes (:func:`scan_pickle`, with :mod:`pickletools`: nothing
   is built, nothing is called) lists every global the file names and measures how deep
   its values nest;
2. a file naming a global outside the allow-list (or a copyreg extension code, or a
   persistent id) is refused with :class:`~amuled_ma.errors.UnsafePickleError`
   naming the file and every such global (``posix.system``), before anything from it runs;
   so is a file nested deeper than :data:`MAX_DEPTH` (hashing a tuple nested a million
   deep, a 1 MB file, crashes CPython's unpickler with a stack overflow);
3. otherwise the real pass runs with the same allow-list (a second guard) in pickle's
   pure-Python reader, so that a signal handler (the command line's SIGTERM) runs between
   two opcodes, never blocked by one long C call. It is bounded in time and memory:

   - the allowed numpy constructors are wrapped: plain numeric dtypes only (no object,
     void, structured or string dtypes), arrays only through ``_reconstruct`` and a checked
     ``BUILD`` state whose data is in the file (so ``numpy.ndarray`` cannot be called on a
     buffer with a forged shape), at most :data:`MAX_ARRAY_ITEMS` entries per array and,
     all arrays together, no more bytes than the file has;
   - dict keys and set items are strings, numbers (integers within +-(2**61 - 2)), or flat
     tuples or frozensets of at most :data:`MAX_KEY_ITEMS` of them, and at most
     :data:`MAX_EQUAL_HASHES` keys of one dict share a hash value (colliding keys make
     Python's dicts quadratic);
   - ``BUILD`` sets the state of arrays and dtypes only; ``OBJ``, ``INST`` and ``NEWOBJ``
     are refused;
   - the process's memory may grow by :data:`MEMORY_PER_BYTE` bytes per byte of the file
     plus :data:`MEMORY_SLACK_BYTES`.

The file is at most :data:`MAX_PICKLE_BYTES`. Callers check the structure they expect
(:mod:`amuled_ma.authors.caches`).
"""

from __future__ import annotations

import io
import math
import os
import pickle
import pickletools
import resource
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from amuled_ma.errors import AuthorsImportError, UnsafePickleError

#: Largest pickle read [bytes]: 8 times the largest published cache (1.95 MB, Driving
#: llama-3.1-70B, read in about 4 s); reading is linear in the file's size.
MAX_PICKLE_BYTES = 16 * 2**20
#: Most memory the values read from one file may take [bytes per byte of the file], plus
#: :data:`MEMORY_SLACK_BYTES`: the 1.95 MB cache grows the process by about 57 MB (29 per
#: byte); checked on the resident set every :data:`MEMORY_CHECK_EVERY` opcodes.
MEMORY_PER_BYTE = 64
#: Memory allowed on top of :data:`MEMORY_PER_BYTE` times the file's size [bytes].
MEMORY_SLACK_BYTES = 64 * 2**20
#: Opcodes between two looks at the process's resident memory.
MEMORY_CHECK_EVERY = 2**15
#: Most entries of one array (the authors' arrays hold one value per action).
MAX_ARRAY_ITEMS = 2**20
#: Deepest nesting of values accepted (the authors' caches nest 9 deep, counting each
#: opcode that wraps values: dict, key tuple, numpy scalar, its arguments, ...).
MAX_DEPTH = 64
#: Most keys of one dict (or items of one set) that may share one hash value. Python's
#: dicts insert keys of equal hash in quadratic time (a 2 MB file of colliding integer keys
#: took over 13 minutes); distinct keys of equal hash do not occur in the caches.
MAX_EQUAL_HASHES = 8
#: Most items of a tuple or frozenset used as a dict key or set item (the caches' keys are
#: observations of 8 or 11 numbers; a key is hashed again on every use).
MAX_KEY_ITEMS = 64
#: Largest integer (in absolute value) accepted in a dict key or set item: below
#: ``sys.hash_info.modulus`` (2**61 - 1), where integers hash to themselves (the caches'
#: keys hold no integers at all).
MAX_KEY_INT = 2**61 - 2
#: numpy dtype kinds a cache may hold: bool, signed and unsigned integers, floats, complex
#: numbers. Void (``V``), object (``O``), structured, string and datetime dtypes are refused.
ALLOWED_DTYPE_KINDS = frozenset("biufc")
#: ``(module, name)`` of every global a cache may name, both numpy spellings
#: (``numpy.core`` before numpy 2, ``numpy._core`` since), plus the builtin sets that
#: pickle protocols below 4 name instead of using their opcodes.
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
#: The first bytes of a Git LFS pointer file (a checkout made without ``git lfs pull``).
_LFS_POINTER = b"version https://git-lfs"


class _Refused(pickle.UnpicklingError):
    """Raised inside the real pass for a global or a numpy value outside the allow-list."""


class _Unbounded(pickle.UnpicklingError):
    """Raised inside the real pass for a value that would cost unbounded time or memory."""


class _NdarrayToken:
    """What ``numpy.ndarray`` resolves to: only accepted as ``_reconstruct``'s first argument."""

    def __call__(self, *_args: Any, **_kwargs: Any) -> Any:
        raise _Refused("numpy.ndarray called directly (only allowed through _reconstruct)")


_NDARRAY = _NdarrayToken()


def _multiarray() -> Any:
    try:
        from numpy._core import multiarray
    except ImportError:  # pragma: no cover - numpy < 2
        from numpy.core import multiarray  # type: ignore[no-redef]
    return multiarray


def _checked_dtype(dtype: Any) -> np.dtype:
    """``dtype`` if it is a plain numeric dtype (:data:`ALLOWED_DTYPE_KINDS`), else refuse."""
    if not isinstance(dtype, np.dtype):
        raise _Refused(f"a dtype that is not a numpy dtype ({type(dtype).__name__})")
    if (
        dtype.hasobject
        or dtype.kind not in ALLOWED_DTYPE_KINDS
        or dtype.fields is not None
        or dtype.subdtype is not None
        or dtype.itemsize > 16
    ):
        what = "object" if dtype.hasobject else "void" if dtype.kind == "V" else "non-numeric"
        raise _Refused(
            f"{what} dtype {dtype!r} (only bool, integer, float and complex numbers are "
            "allowed; object, void and structured dtypes are refused)"
        )
    return dtype


def _shape(shape: Any) -> tuple[int, ...]:
    if not (
        isinstance(shape, tuple)
        and len(shape) <= 32
        and all(type(n) is int and 0 <= n <= MAX_ARRAY_ITEMS for n in shape)
    ):
        raise _Refused(f"array of shape {shape!r}")
    items = 1
    for n in shape:
        items *= n
    if items > MAX_ARRAY_ITEMS:
        raise _Refused(f"array of shape {shape!r} (more than {MAX_ARRAY_ITEMS:,} entries)")
    return shape


def _check_key(key: Any) -> None:
    """Refuse a dict key or set item whose hashing could cost more than a flat observation's."""
    kind = type(key)
    if kind is str or kind is bytes or kind is float or kind is bool or key is None:
        return
    if kind is int:
        if -MAX_KEY_INT <= key <= MAX_KEY_INT:
            return
        raise _Unbounded(
            f"an integer dict key or set item of {key.bit_length()} bits, beyond +-(2**61 - 2) "
            "(multiples of 2**61 - 1 all hash alike)"
        )
    if isinstance(key, np.generic):
        return  # built by _scalar: a number of an allowed dtype
    if kind is tuple or kind is frozenset:
        if len(key) > MAX_KEY_ITEMS:
            raise _Unbounded(
                f"a dict key or set item of {len(key):,} values (at most {MAX_KEY_ITEMS})"
            )
        for item in key:
            if type(item) in (tuple, frozenset):
                raise _Unbounded("a dict key or set item nested in another (keys are flat)")
            _check_key(item)
        return
    raise _Refused(
        f"a dict key or set item of type {kind.__name__} (keys are strings, numbers, and flat "
        "tuples or frozensets of them)"
    )


class _HashCounter:
    """Keys of one dict or set by hash value: refuses more than :data:`MAX_EQUAL_HASHES`."""

    __slots__ = ("counts", "owner")

    def __init__(self, owner: Any) -> None:
        self.owner = owner  # kept alive, so that its id is not reused while counted
        self.counts: dict[int, int] = {}

    def admit(self, key: Any) -> None:
        _check_key(key)
        h = hash(key)
        n = self.counts.get(h, 0) + 1
        if n > MAX_EQUAL_HASHES:
            raise _Unbounded(
                f"more than {MAX_EQUAL_HASHES} keys of one dict or set share one hash value "
                "(keys crafted to collide make reading take quadratic time)"
            )
        self.counts[h] = n


_DISPATCH = pickle._Unpickler.dispatch  # type: ignore[attr-defined]


def _opcode(name: str) -> int:
    return getattr(pickle, name)[0]


class AllowListUnpickler(pickle._Unpickler):  # type: ignore[name-defined,misc]
    """A pure-Python :class:`pickle.Unpickler` for :data:`ALLOWED_GLOBALS`, bounded.

    Any other global raises :class:`pickle.UnpicklingError` when the file names it, before
    it could be called. Allowed numpy globals resolve to checked methods (module doc).
    Pickle's own Python reader (not the C one) runs the opcodes, so a signal handler (the
    command line's SIGTERM) runs between two opcodes; the opcodes that hash (dict, set and
    frozenset building) check their keys and count equal hashes, ``BUILD`` only rebuilds
    arrays and dtypes after checking their state, and arrays together hold at most
    ``max_array_bytes`` bytes.

    Args:
        file: The pickle's bytes, as a binary file.
        max_array_bytes: Most bytes of all arrays together (the file's size: an array's
            data is in the file).

    """

    dispatch: ClassVar[dict[int, Any]] = dict(_DISPATCH)

    def __init__(self, file: Any, *, max_array_bytes: int = MAX_PICKLE_BYTES) -> None:
        super().__init__(file)
        self.array_bytes_left = max_array_bytes
        self._counters: dict[int, _HashCounter] = {}
        self._targets: dict[str, Any] = {
            "scalar": self._scalar,
            "_reconstruct": self._reconstruct,
            "ndarray": _NDARRAY,
            "dtype": self._dtype,
            "frozenset": self._frozenset,
            "set": self._set,
        }

    def load(self, *, max_memory: int | None = None) -> Any:
        """Read the pickle: :meth:`pickle._Unpickler.load`, looking at memory as it goes.

        Args:
            max_memory: Most bytes the process's resident memory may grow by (None: no
                limit); looked at every :data:`MEMORY_CHECK_EVERY` opcodes.

        """
        self._unframer = pickle._Unframer(self._file_read, self._file_readline)  # type: ignore[attr-defined]
        self.read = self._unframer.read
        self.readinto = self._unframer.readinto
        self.readline = self._unframer.readline
        self.metastack = []
        self.stack: list[Any] = []
        self.append = self.stack.append
        self.proto = 0
        read = self.read
        dispatch = self.dispatch
        start = _resident_bytes() if max_memory is not None else None
        count = 0
        try:
            while True:
                key = read(1)
                if not key:
                    raise EOFError
                dispatch[key[0]](self)
                count += 1
                if start is not None and count % MEMORY_CHECK_EVERY == 0:
                    grown = _resident_bytes() - start
                    if max_memory is not None and grown > max_memory:
                        raise _Unbounded(
                            f"its values take more than {max_memory // 2**20:,} MiB of memory "
                            f"({MEMORY_PER_BYTE} bytes per byte of the file, plus "
                            f"{MEMORY_SLACK_BYTES // 2**20} MiB)"
                        )
        except pickle._Stop as stop:  # type: ignore[attr-defined]
            return stop.value

    def find_class(self, module: str, name: str) -> Any:
        """Return the allowed object for ``module.name``; refuse everything else."""
        if (module, name) not in ALLOWED_GLOBALS:
            raise _Refused(f"global {module}.{name} is not allowed")
        return self._targets[name]

    # -- the allowed globals -------------------------------------------------------------
    def _spend(self, nbytes: int, what: str) -> None:
        if nbytes > self.array_bytes_left:
            raise _Unbounded(
                f"{what} of {nbytes:,} bytes, more than the file's size allows (arrays hold "
                "at most as many bytes as the file has)"
            )
        self.array_bytes_left -= nbytes

    def _scalar(self, dtype: Any, *args: Any) -> Any:
        dtype = _checked_dtype(dtype)
        if len(args) != 1 or type(args[0]) is not bytes or len(args[0]) != dtype.itemsize:
            raise _Refused(f"numpy scalar of dtype {dtype!r} not built from its bytes")
        return _multiarray().scalar(dtype, *args)

    def _reconstruct(self, subtype: Any, shape: Any, dtype: Any) -> Any:
        if subtype is not _NDARRAY:
            raise _Refused("_reconstruct of anything but numpy.ndarray")
        shape = _shape(shape)
        if type(dtype) is bytes and len(dtype) <= 8:
            dtype = np.dtype(dtype.decode("ascii"))
        dtype = _checked_dtype(dtype)
        self._spend(math.prod(shape) * dtype.itemsize, f"array of shape {shape}")
        return _multiarray()._reconstruct(np.ndarray, shape, dtype)

    def _dtype(self, spec: Any, align: Any = False, copy: Any = True) -> np.dtype:
        if type(spec) is not str or len(spec) > 8 or align is not False:
            raise _Refused(f"dtype({spec!r}, {align!r}) (only plain numeric type codes)")
        try:
            dtype = np.dtype(spec)
        except TypeError as error:
            raise _Refused(f"dtype {spec!r} ({error})") from error
        _checked_dtype(dtype)
        return np.dtype(spec, align=False, copy=True)  # a copy: BUILD never alters numpy's own

    def _frozenset(self, items: Any = ()) -> frozenset:
        return frozenset(self._admitted(list(items)))

    def _set(self, items: Any = ()) -> set:
        return set(self._admitted(list(items)))

    def _admitted(self, items: list[Any]) -> list[Any]:
        counter = _HashCounter(None)
        for item in items:
            counter.admit(item)
        return items

    # -- opcodes that hash, build or instantiate -----------------------------------------
    def _counter(self, container: Any) -> _HashCounter:
        counter = self._counters.get(id(container))
        if counter is None or counter.owner is not container:
            counter = self._counters[id(container)] = _HashCounter(container)
        return counter

    def _setitems(self, target: Any, items: list[Any]) -> None:
        if type(target) is not dict:
            raise _Refused(f"SETITEM on a {type(target).__name__}")
        counter = self._counter(target)
        for i in range(0, len(items) - 1, 2):
            counter.admit(items[i])
            target[items[i]] = items[i + 1]

    def load_setitem(self) -> None:
        """``SETITEM``: one key and value into the dict below them."""
        stack = self.stack
        value = stack.pop()
        key = stack.pop()
        self._setitems(stack[-1], [key, value])

    def load_setitems(self) -> None:
        """``SETITEMS``: the keys and values above the mark into the dict below it."""
        items = self.pop_mark()
        self._setitems(self.stack[-1], items)

    def load_dict(self) -> None:
        """``DICT``: a new dict of the keys and values above the mark."""
        items = self.pop_mark()
        target: dict[Any, Any] = {}
        self._setitems(target, items)
        self.append(target)

    def load_additems(self) -> None:
        """``ADDITEMS``: the items above the mark into the set below it."""
        items = self.pop_mark()
        target = self.stack[-1]
        if type(target) is not set:
            raise _Refused(f"ADDITEMS on a {type(target).__name__}")
        counter = self._counter(target)
        for item in items:
            counter.admit(item)
            target.add(item)

    def load_frozenset(self) -> None:
        """``FROZENSET``: a frozenset of the items above the mark."""
        items = self.pop_mark()  # before self.append is read: pop_mark rebinds it
        self.append(frozenset(self._admitted(items)))

    def load_build(self) -> None:
        """``BUILD``: only an array's or a dtype's state, checked before it is set."""
        stack = self.stack
        state = stack.pop()
        inst = stack[-1]
        if type(inst) is np.ndarray:
            self._check_array_state(state)
        elif isinstance(inst, np.dtype):
            _check_dtype_state(state)
        else:
            raise _Refused(f"BUILD of a {type(inst).__name__} (only arrays and dtypes)")
        inst.__setstate__(state)
        if isinstance(inst, np.dtype):
            _checked_dtype(inst)

    def _check_array_state(self, state: Any) -> None:
        if not (isinstance(state, tuple) and len(state) == 5 and state[0] == 1):
            raise _Refused("an array state that is not (1, shape, dtype, fortran, bytes)")
        _, shape, dtype, fortran, data = state
        shape = _shape(shape)
        dtype = _checked_dtype(dtype)
        nbytes = math.prod(shape) * dtype.itemsize
        if type(fortran) is not bool or type(data) is not bytes or len(data) != nbytes:
            raise _Refused(
                f"an array state of shape {shape} and dtype {dtype} without its "
                f"{nbytes:,} bytes of data"
            )
        self._spend(nbytes, f"array of shape {shape}")

    def _refuse_opcode(self) -> None:
        raise _Refused("an object built by OBJ, INST or NEWOBJ (caches need none)")

    for _name in ("SETITEM", "SETITEMS", "DICT", "ADDITEMS", "FROZENSET", "BUILD"):
        dispatch[_opcode(_name)] = locals()[f"load_{_name.lower()}"]
    for _name in ("OBJ", "INST", "NEWOBJ", "NEWOBJ_EX"):
        dispatch[_opcode(_name)] = _refuse_opcode
    del _name


def _check_dtype_state(state: Any) -> None:
    """A numeric dtype's state: ``(3, byte order, None, None, None, -1, -1, 0)``."""
    if not (
        isinstance(state, tuple)
        and len(state) == 8
        and state[0] == 3
        and state[1] in ("<", ">", "|", "=")
        and state[2:5] == (None, None, None)
        and state[5:] == (-1, -1, 0)
    ):
        raise _Refused(f"a dtype state {_short(state)} (only plain numeric dtypes)")


def _resident_bytes() -> int:
    """The process's resident memory now (Linux ``/proc/self/statm``), else its peak."""
    try:
        with open("/proc/self/statm", "rb") as handle:
            return int(handle.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


#: Opcodes that add values to the container below them on the stack (which keeps its depth).
_MODIFY = frozenset({"APPEND", "APPENDS", "SETITEM", "SETITEMS", "ADDITEMS", "BUILD"})
_PUT, _MEMOIZE, _GET, _MARK, _PUSH, _NOTHING, _OTHER = range(7)


def _opcode_table() -> dict[str, tuple[int, bool, int, int, bool]]:
    """Per opcode: ``(kind, pops to a mark, fixed items popped, items pushed, modifies)``."""
    mark = pickletools.markobject
    table = {}
    for op in pickletools.opcodes:
        before, after = op.stack_before, op.stack_after
        if op.name in ("PUT", "BINPUT", "LONG_BINPUT"):
            kind = _PUT
        elif op.name == "MEMOIZE":
            kind = _MEMOIZE
        elif op.name in ("GET", "BINGET", "LONG_BINGET"):
            kind = _GET
        elif op.name == "MARK":
            kind = _MARK
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


def _depth(item: Any) -> int:
    return item if type(item) is int else 1  # a string pushed by the file


@dataclass
class PickleScan:
    """What a pickle holds, read from its opcodes alone.

    Attributes:
        globals: ``module.name`` of every global it names, in order of appearance
            (``copyreg extension N`` and ``persistent id`` for those opcodes).
        depth: How deep its values nest (stopped at ``MAX_DEPTH + 1``).

    """

    globals: list[str]
    depth: int


def scan_pickle(data: bytes, *, max_depth: int = MAX_DEPTH) -> PickleScan:
    """Read a pickle's opcodes (nothing is built or called): its globals and its depth.

    The stack is followed abstractly: each entry is its nesting depth, or the text of a
    string the file pushed (so that ``STACK_GLOBAL`` can name its module and name).

    Args:
        data: The pickle's bytes.
        max_depth: Stop reading once the depth exceeds it.

    Returns:
        The globals named and the depth reached.

    Raises:
        ValueError: The bytes are not a well-formed pickle.

    """
    stack: list[Any] = []
    marks: list[int] = []
    memo: dict[int, Any] = {}
    found: list[str] = []
    deepest = 0
    try:
        for op, arg, _pos in pickletools.genops(data):
            kind, to_mark, fixed, pushed, modifies = _OPCODES[op.name]
            if kind == _PUSH:
                stack.append(arg if type(arg) is str else 1)
                continue
            if kind == _PUT:
                memo[arg] = stack[-1]
                continue
            if kind == _GET:
                stack.append(memo[arg])
                continue
            if kind == _MEMOIZE:
                memo[len(memo)] = stack[-1]
                continue
            if kind == _MARK:
                marks.append(len(stack))
                continue
            if kind == _NOTHING:
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
    return PickleScan(globals=found, depth=deepest)


def pickle_globals(data: bytes) -> list[str]:
    """Every global a pickle names, in order of appearance, found without running any.

    Raises:
        ValueError: The bytes are not a well-formed pickle.

    """
    return scan_pickle(data).globals


def load_pickle(path: str | Path, *, max_bytes: int = MAX_PICKLE_BYTES) -> Any:
    """Load a pickle that may only hold numpy arrays/scalars in builtin containers.

    Args:
        path: The pickle file.
        max_bytes: Largest file accepted.

    Returns:
        The unpickled object.

    Raises:
        UnsafePickleError: The file names a global outside :data:`ALLOWED_GLOBALS`; the
            message names the file and every such global. Nothing from the file ran.
        AuthorsImportError: The file is missing, too large, a Git LFS pointer, or not a
            readable pickle.

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
    if scan.depth > MAX_DEPTH:
        raise AuthorsImportError(
            f"{path}: refusing to unpickle: its values nest more than {MAX_DEPTH} deep (an "
            "LLM cache nests about 9; deeper nesting can crash the reader); nothing from the "
            "file was run"
        )
    try:
        return AllowListUnpickler(io.BytesIO(data), max_array_bytes=len(data)).load(
            max_memory=MEMORY_PER_BYTE * len(data) + MEMORY_SLACK_BYTES
        )
    except _Unbounded as error:
        raise AuthorsImportError(
            f"{path}: refusing to unpickle: {error}; is it the authors' file? Nothing from "
            "the file was run"
        ) from error
    except _Refused as error:
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
