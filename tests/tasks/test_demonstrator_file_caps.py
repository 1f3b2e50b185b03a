"""A demonstrator ``.npz`` is sized from its headers before ``np.load`` allocates anything.

``np.load`` allocates the array a ``.npy`` header claims before it reads the data: a file
of a few hundred bytes claiming 2^40 entries raised ``MemoryError``, and a 1.46 MB
compressed file took 3.5 GB. Each case is one line naming the file, within a second.
"""

from __future__ import annotations

import io
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from amuled_ma.tasks.demonstrators import DemonstratorBelief, DemonstratorCacheError
from amuled_ma.tasks.demonstrators import table as table_module


def npy_header(shape: tuple[int, ...], dtype: str = "<i8") -> bytes:
    """A version 1.0 ``.npy`` header, as numpy's format writes it."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buffer, {"descr": dtype, "fortran_order": False, "shape": shape}
    )
    return buffer.getvalue()  # the magic string, then the header


def saved(tmp_path: Path) -> Path:
    settings = {"task": "findmilk", "seed": 1, "episodes": 1}
    states = torch.arange(100, dtype=torch.int64)
    counts = torch.ones(100, 4, dtype=torch.int64)
    return DemonstratorBelief("findmilk", states, counts, settings).save(tmp_path / "t.npz")


def one_line(path: Path) -> str:
    start = time.perf_counter()
    with pytest.raises(DemonstratorCacheError) as caught:
        DemonstratorBelief.load(path)
    assert time.perf_counter() - start < 1.0
    line = str(caught.value)
    assert "\n" not in line and line.startswith(f"{path}: "), line
    return line


def test_a_header_claiming_2_to_the_40_entries_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "claims.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("states.npy", npy_header((2**40,)) + b"\0" * 64)
    line = one_line(path)
    assert "states.npy (shape (1099511627776,) of int64)" in line, line
    assert "claims 8,796,093,022,208 bytes but its member holds" in line, line  # 8 x 2^40


def test_arrays_over_the_cap_are_refused_from_their_headers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = saved(tmp_path)
    with np.load(path) as data:  # numpy's own count of the bytes they take
        nbytes = sum(data[name].nbytes for name in data.files)
    monkeypatch.setattr(table_module, "MAX_TABLE_BYTES", nbytes - 1)
    line = one_line(path)
    assert f"more than the {nbytes - 1:,} a demonstrator table may take" in line, line
    assert "it is not loaded; delete it to rebuild the demonstrator" in line
    monkeypatch.setattr(table_module, "MAX_TABLE_BYTES", nbytes)
    assert DemonstratorBelief.load(path).counts.shape == (100, 4)


def test_a_compressed_bomb_is_refused_without_unpacking(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """64 MiB of zeros compress to about 64 KB; the header is read, not the data."""
    path = tmp_path / "bomb.npz"
    data = npy_header((8 * 2**20,)) + bytes(64 * 2**20)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("states.npy", data)
    assert path.stat().st_size < 2**20
    monkeypatch.setattr(table_module, "MAX_TABLE_BYTES", 2**20)
    line = one_line(path)
    assert "would take 67,108,864 bytes of memory or more" in line, line  # 8 x 8 MiB


def test_an_object_array_and_a_non_npy_member_are_one_line(tmp_path: Path) -> None:
    objects = tmp_path / "objects.npz"
    with zipfile.ZipFile(objects, "w") as archive:
        archive.writestr("states.npy", npy_header((1,), "|O") + b"\0" * 8)
    assert "holds Python objects" in one_line(objects)
    text = tmp_path / "text.npz"
    with zipfile.ZipFile(text, "w") as archive:
        archive.writestr("states.npy", b"hello, not an array")
    assert "not a readable demonstrator cache" in one_line(text)
