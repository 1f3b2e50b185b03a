"""Hostile LLM-cache pickles, written opcode by opcode (no Python object is built here).

- :func:`colliding_int_keys`: a dict whose integer keys all hash alike (``k * (2**61 - 1)``
  hashes to 0 for every ``k``): CPython's unpickler inserts them in quadratic time and,
  being one C call, does not run a signal handler until it is done.
- :func:`colliding_tuple_keys`: the same with observation-like keys, tuples of 8 such ints.
- :func:`void_array`: about 1 KB that asks numpy for a void-dtype array of ``2**20`` items
  of 4,600 bytes each (4.8 GB, zero-filled).
- :func:`huge_void_build`: an empty array whose ``BUILD`` state declares a huge shape.
"""

from __future__ import annotations

import struct

#: ``sys.hash_info.modulus`` on 64-bit CPython: ``hash(k * P) == 0`` for every int ``k``.
P = 2**61 - 1

PROTO4 = b"\x80\x04"
EMPTY_DICT, MARK, SETITEMS, NONE, STOP = b"}", b"(", b"u", b"N", b"."
TUPLE = b"t"


def _long1(value: int) -> bytes:
    raw = value.to_bytes((value.bit_length() + 8) // 8, "little", signed=True)
    assert len(raw) < 256
    return b"\x8a" + bytes([len(raw)]) + raw


def colliding_int_keys(size: int) -> bytes:
    """A pickled ``{k * P: None, ...}`` of about ``size`` bytes (about 11 bytes per key)."""
    body = bytearray()
    k = 1
    while len(body) < size:
        body += _long1(k * P) + NONE
        k += 1
    return PROTO4 + EMPTY_DICT + MARK + bytes(body) + SETITEMS + STOP


def colliding_tuple_keys(size: int) -> bytes:
    """A pickled ``{(k * P, 0, 0, ..., 0): None, ...}`` (8-tuples) of about ``size`` bytes."""
    body = bytearray()
    k = 1
    zero = b"K\x00"  # BININT1 0
    while len(body) < size:
        body += MARK + _long1(k * P) + zero * 7 + TUPLE + NONE
        k += 1
    return PROTO4 + EMPTY_DICT + MARK + bytes(body) + SETITEMS + STOP


def _global(module: str, name: str) -> bytes:
    return b"c" + module.encode() + b"\n" + name.encode() + b"\n"


def _unicode(text: str) -> bytes:
    raw = text.encode()
    return b"X" + struct.pack("<I", len(raw)) + raw


def _dtype(spec: str) -> bytes:
    """``numpy.dtype(spec, False, True)``."""
    return _global("numpy", "dtype") + _unicode(spec) + b"\x89\x88\x87R"


def void_array(items: int = 2**20, itemsize: int = 4600) -> bytes:
    """``_reconstruct(ndarray, (items,), dtype('V<itemsize>'))`` inside a cache-like dict."""
    call = (
        _global("numpy.core.multiarray", "_reconstruct")
        + _global("numpy", "ndarray")
        + b"J"
        + struct.pack("<i", items)
        + b"\x85"  # TUPLE1: the shape
        + _dtype(f"V{itemsize}")
        + b"\x87R"  # TUPLE3, REDUCE
    )
    key = MARK + b"G" + struct.pack(">d", 1.0) + TUPLE
    return PROTO4 + EMPTY_DICT + key + call + b"s" + STOP


def huge_void_build(items: int = 2**20, itemsize: int = 4600) -> bytes:
    """An empty array rebuilt by ``BUILD`` with the state ``(1, (items,), V, False, b"")``."""
    empty = (
        _global("numpy.core.multiarray", "_reconstruct")
        + _global("numpy", "ndarray")
        + b"K\x00\x85"  # (0,)
        + b"C\x01b"  # SHORT_BINBYTES b'b'
        + b"\x87R"
    )
    state = (
        MARK
        + b"K\x01"
        + b"J"
        + struct.pack("<i", items)
        + b"\x85"
        + _dtype(f"V{itemsize}")
        + b"\x89"
        + b"C\x00"
        + TUPLE
    )
    return PROTO4 + empty + state + b"b" + STOP


def many_sets(size: int) -> bytes:
    """A list of about ``size`` empty sets (1 byte each in the file, about 216 in memory)."""
    return PROTO4 + b"]" + MARK + b"\x8f" * size + b"e" + STOP


def colliding_float_keys() -> bytes:
    """``{2.0 ** (61 * j): None for j in range(17)}``: 17 floats of equal hash (1)."""
    body = b"".join(b"G" + struct.pack(">d", 2.0 ** (61 * j)) + NONE for j in range(17))
    return PROTO4 + EMPTY_DICT + MARK + body + SETITEMS + STOP


def memoized_key_sets(calls: int, width: int = 64, copies: int = 6) -> bytes:
    """``set(L)`` ``calls`` times, ``L`` one memoized list of ``copies`` refs to a ``width``-tuple.

    Five opcodes (7 bytes) a call make the reader check and hash ``copies x (width + 1)``
    values: within the opcode budget, a 16 MiB file of them spends minutes of CPU unless
    the key work is counted.
    """
    item = b"".join(b"G" + struct.pack(">d", float(i)) for i in range(width))
    tuple_ = MARK + item + b"t" + b"q\xf1"  # TUPLE, BINPUT 0xf1
    list_ = b"]q\xf2" + MARK + b"h\xf1" * copies + b"e"  # EMPTY_LIST, BINPUT, BINGETs, APPENDS
    set_global = _global("builtins", "set") + b"q\xf3"
    call = b"h\xf3h\xf2\x85R0"  # BINGET set, BINGET L, TUPLE1, REDUCE, POP
    return PROTO4 + tuple_ + list_ + set_global + call * calls + NONE + STOP
