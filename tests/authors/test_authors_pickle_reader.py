"""The bounded reader builds what pickle builds, for the opcodes a cache uses, and no more."""

import ast
import pickle
from pathlib import Path

import numpy as np
import pytest

from amuled_ma.authors import unpickle
from amuled_ma.authors.unpickle import load_pickle
from amuled_ma.errors import AuthorsImportError, UnsafePickleError

PLAIN = {
    "a": [1, -2, 2**40, -(2**70), 2.5, None, True, False, "é\u20ac", "", (), (1,)],
    (1.5, "k", 3): {"t2": (1, 2), "t3": (1, 2, 3), "t4": (1, 2, 3, 4)},
    "sets": [frozenset({1, "x"}), {3, 4}, frozenset()],
    "dict": {i: str(i) for i in range(1200)},  # more than one SETITEMS batch
}


def shared() -> list:
    inner = [1, 2]
    return [inner, inner, (inner,)]


@pytest.mark.parametrize("protocol", [0, 1, 2, 3, 4, 5])
def test_plain_values_load_as_pickle_loads_them(tmp_path, protocol):
    path = tmp_path / "plain.pickle"
    path.write_bytes(pickle.dumps([PLAIN, shared()], protocol=protocol, fix_imports=False))
    loaded = load_pickle(path)
    assert loaded == pickle.loads(path.read_bytes())
    assert loaded[1][0] is loaded[1][1] is loaded[1][2][0]  # the memo shares as pickle does
    if protocol >= 3:
        path.write_bytes(pickle.dumps({b"k": b"v" * 300}, protocol=protocol))
        assert load_pickle(path) == {b"k": b"v" * 300}


@pytest.mark.parametrize("protocol", [3, 4])
def test_numpy_values_identical_to_pickles(tmp_path, protocol):
    values = [
        np.arange(12, dtype=">i4").reshape(3, 4),
        np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        np.array([True, False]),
        np.zeros(0, dtype=np.complex64),
        np.float32(0.1),
        np.uint8(7),
        np.complex128(1 + 2j),
    ]
    path = tmp_path / "np.pickle"
    path.write_bytes(pickle.dumps(values, protocol=protocol))
    loaded = load_pickle(path)
    for got, want in zip(loaded, pickle.loads(path.read_bytes()), strict=True):
        assert type(got) is type(want)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
        if isinstance(want, np.ndarray):
            assert got.shape == want.shape and got.strides == want.strides
            assert got.flags.writeable == want.flags.writeable


@pytest.mark.parametrize(
    ("data", "opcode"),
    [
        (pickle.dumps(bytearray(b"ab"), protocol=5), "BYTEARRAY8"),
        (b"U\x02ab.", "SHORT_BINSTRING"),  # a Python 2 str
        (b"S'ab'\np0\n.", "STRING"),
    ],
)
def test_opcodes_a_cache_does_not_use_are_refused(tmp_path, data, opcode):
    path = tmp_path / "odd.pickle"
    path.write_bytes(data)
    with pytest.raises(UnsafePickleError, match=f"the opcode {opcode} "):
        load_pickle(path)


def test_reduce_only_calls_allowed_globals(tmp_path):
    path = tmp_path / "call.pickle"
    path.write_bytes(b"\x80\x04](K\x01t\x94R.")  # a list called on (1,)
    with pytest.raises(UnsafePickleError, match="REDUCE on a list"):
        load_pickle(path)


def test_set_calls_hash_no_more_items_than_the_file_has_bytes(tmp_path):
    # one list of 1,000 items, then set() of it 2,000 times: 8 bytes a call, 1,000 items each
    items = b"".join(b"J" + i.to_bytes(4, "little") for i in range(1000))
    call = b"cbuiltins\nset\nh\x00\x85R0"  # GLOBAL, BINGET 0, TUPLE1, REDUCE, POP
    data = b"\x80\x03](" + items + b"eq\x00" + call * 2000 + b"."
    path = tmp_path / "sets.pickle"
    path.write_bytes(data)
    with pytest.raises(AuthorsImportError, match=r"set\(\) and frozenset\(\) calls") as info:
        load_pickle(path)
    assert not isinstance(info.value, UnsafePickleError)
    path.write_bytes(b"\x80\x03](" + items + b"eq\x00" + call * 2 + call[:-1] + b".")
    assert load_pickle(path) == set(range(1000))


def test_the_reader_uses_no_private_pickle_name():
    for module in (unpickle,):
        source = Path(module.__file__).read_text(encoding="utf-8")
        assert "pickle._" not in source
        tree = ast.parse(source)
        assert not [
            node.attr
            for node in ast.walk(tree)
            if isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id in ("pickle", "pickletools")
            and node.attr.startswith("_")
        ]
