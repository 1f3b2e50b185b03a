"""The allow-list unpickler: numpy values load, anything else is refused before it runs."""

import os
import pickle

import numpy as np
import pytest
from authors_fakes import findmilk_cache, write_pickle

from amuled_ma.authors.unpickle import load_pickle, scan_pickle
from amuled_ma.errors import AuthorsImportError, UnsafePickleError


class TouchMarker:
    """Unpickling this runs ``os.system('touch <marker>')``: the classic pickle exploit."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def evil_cache(marker):
    """A cache that looks like the authors' one, with the exploit inside one value."""
    cache = findmilk_cache(states=2)
    key = next(iter(cache))
    cache[key]["care"] = TouchMarker(marker)
    return cache


def test_plain_pickle_would_run_the_exploit(tmp_path):
    """Control: the standard unpickler runs the command (so the refusal below matters)."""
    marker = tmp_path / "marker"
    data = pickle.dumps(evil_cache(marker), protocol=4)
    pickle.loads(data)  # on purpose: this is what the file does to a plain reader
    assert marker.exists()


def test_exploit_refused_naming_file_and_global_nothing_runs(tmp_path):
    marker = tmp_path / "marker"
    path = write_pickle(tmp_path / "gpt-4o-mini_llm_cache.pickle", evil_cache(marker))
    with pytest.raises(UnsafePickleError) as info:
        load_pickle(path)
    message = str(info.value)
    assert str(path) in message
    assert "posix.system" in message
    assert "nothing from the file was run" in message
    assert not marker.exists()


def test_globals_are_listed_without_running_any(tmp_path):
    marker = tmp_path / "marker"
    data = pickle.dumps([np.float32(1.0), TouchMarker(marker)], protocol=4)
    found = scan_pickle(data).globals
    assert found == ["numpy._core.multiarray.scalar", "numpy.dtype", "posix.system"]
    assert not marker.exists()


def test_numpy_values_load_in_both_numpy_spellings(tmp_path):
    cache = findmilk_cache(states=3)
    path = write_pickle(tmp_path / "new.pickle", cache)  # numpy 2: numpy._core.multiarray
    loaded = load_pickle(path)
    assert list(loaded) == list(cache)
    for key, entry in cache.items():
        assert all(type(x) is np.float32 for x in next(k for k in loaded if k == key))
        for name in ("care", "moral"):
            np.testing.assert_array_equal(loaded[key][name], entry[name])
            assert loaded[key][name].dtype == np.float64
        assert loaded[key]["rewards"] == entry["rewards"]
    # the authors' files name numpy.core.multiarray (numpy < 2): rewrite our pickle so
    old = old_numpy_spelling(pickle.dumps({(np.float32(3.0),): np.array([0.25, 0.75])}, 4))
    (tmp_path / "old.pickle").write_bytes(old)
    assert scan_pickle(old).globals[0] == "numpy.core.multiarray.scalar"
    loaded = load_pickle(tmp_path / "old.pickle")
    np.testing.assert_array_equal(loaded[(3.0,)], [0.25, 0.75])


def old_numpy_spelling(data: bytes) -> bytes:
    """A protocol-4 pickle with ``numpy._core.multiarray`` renamed ``numpy.core.multiarray``.

    The module name is a SHORT_BINUNICODE (length byte 0x16 -> 0x15), inside one FRAME whose
    8-byte length shrinks by one per renamed name.
    """
    new, old = b"\x8c\x16numpy._core.multiarray", b"\x8c\x15numpy.core.multiarray"
    count = data.count(new)
    assert count and data[2] == 0x95  # PROTO 4, then one FRAME
    length = int.from_bytes(data[3:11], "little") - count
    return data[:3] + length.to_bytes(8, "little") + data[11:].replace(new, old)


def test_object_arrays_refused_although_their_globals_are_allowed(tmp_path):
    path = write_pickle(tmp_path / "obj.pickle", {"a": np.array([1, "x"], dtype=object)})
    assert set(scan_pickle(path.read_bytes()).globals) <= {
        "numpy._core.multiarray._reconstruct",
        "numpy.ndarray",
        "numpy.dtype",
    }
    with pytest.raises(UnsafePickleError, match="object dtype"):
        load_pickle(path)


class DirectNdarray:
    def __reduce__(self):
        return (np.ndarray, ((10**6,), "f8"))


def test_ndarray_cannot_be_called_directly(tmp_path):
    path = write_pickle(tmp_path / "nd.pickle", [DirectNdarray()])
    with pytest.raises(UnsafePickleError, match=r"numpy\.ndarray called directly"):
        load_pickle(path)


def test_size_bound_and_lfs_pointer_and_damage(tmp_path):
    path = write_pickle(tmp_path / "c.pickle", findmilk_cache(states=2))
    with pytest.raises(AuthorsImportError, match="more than the 100 accepted"):
        load_pickle(path, max_bytes=100)
    lfs = tmp_path / "lfs.pickle"
    lfs.write_text("version https://git-lfs.github.com/spec/v1\noid sha256:abc\nsize 12\n")
    with pytest.raises(AuthorsImportError, match="git lfs pull"):
        load_pickle(lfs)
    cut = tmp_path / "cut.pickle"
    cut.write_bytes(path.read_bytes()[:200])
    with pytest.raises(AuthorsImportError, match="not a readable pickle") as info:
        load_pickle(cut)
    assert not isinstance(info.value, UnsafePickleError)
    with pytest.raises(AuthorsImportError, match="cannot read"):
        load_pickle(tmp_path / "missing.pickle")


def test_deep_nesting_refused_before_it_can_crash_the_reader(tmp_path):
    # a dict whose key is a tuple nested a million deep: about 1 MB, and hashing that key
    # overflows CPython's C stack (a plain pickle.loads of it is a segmentation fault)
    deep = tmp_path / "deep.pickle"
    deep.write_bytes(b"\x80\x04}" + b")" + b"\x85" * 1_000_000 + b"Ns.")
    with pytest.raises(AuthorsImportError, match="nest more than 64 deep"):
        load_pickle(deep)
    assert scan_pickle(deep.read_bytes()).depth == 65  # the scan stops at the limit
    assert scan_pickle(pickle.dumps(findmilk_cache(states=2), protocol=4)).depth < 16


def test_persistent_ids_and_extension_codes_refused(tmp_path):
    path = tmp_path / "persid.pickle"
    path.write_bytes(b"\x80\x04\x8c\x01x\x94Q.")  # BINPERSID: asks the reader for an object
    with pytest.raises(UnsafePickleError, match="persistent id"):
        load_pickle(path)
    path.write_bytes(b"\x80\x04\x82\x01.")  # EXT1: a global by copyreg's extension code
    with pytest.raises(UnsafePickleError, match="copyreg extension 1"):
        load_pickle(path)
