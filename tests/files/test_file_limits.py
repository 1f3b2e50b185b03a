"""The shared size caps: a file over its cap is refused from its size, unread.

Over-cap files are sparse (``truncate``): gigabytes that take no disk and no time.
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import pytest
from sparse_files import sparse

from amuled_ma.errors import AmuledError, PromptError
from amuled_ma.files.limits import (
    check_size,
    read_bounded_bytes,
    read_line,
    too_large,
)
from amuled_ma.files.resources import read_text


def test_the_refusal_is_one_line_with_file_size_cap_and_fix() -> None:
    line = too_large("x.json: the recording", 2_000_000, 1_000_000, "recording", fix="fix it")
    assert line == (
        "x.json: the recording is 2,000,000 bytes, more than the 1,000,000 a recording may "
        "be; it is not read; fix it"
    )
    line = too_large("f", 3, 2, "export line", note="why", fix="fix")
    assert "more than the 2 an export line may be (why); it is not read; fix" in line


def test_a_10_gb_file_is_refused_from_its_size_without_reading(tmp_path: Path) -> None:
    big = sparse(tmp_path / "big.bin", 10 * 2**30)
    start = time.perf_counter()
    with pytest.raises(PromptError) as info:
        read_bounded_bytes(big, 2**20, "state prompt template", error=PromptError)
    with pytest.raises(AmuledError, match="is 10,737,418,240 bytes, more than the 1,048,576"):
        check_size(big, 2**20, "checkpoint")
    assert time.perf_counter() - start < 0.5
    message = str(info.value)
    assert message.startswith(f"{big}: the state prompt template is 10,737,418,240 bytes")
    assert message.endswith("a state prompt template may be; it is not read; is it the right file?")


def test_a_file_at_its_cap_is_read(tmp_path: Path) -> None:
    path = tmp_path / "f"
    path.write_bytes(b"a" * 100)
    assert read_bounded_bytes(path, 100, "file") == b"a" * 100
    assert check_size(path, 100, "file") == 100
    with pytest.raises(AmuledError, match="is 100 bytes, more than the 99"):
        read_bounded_bytes(path, 99, "file")


def test_a_file_that_reports_no_size_is_cut_at_the_cap() -> None:
    # /proc files report 0 bytes: the cap still holds, from what is read
    with pytest.raises(AmuledError) as info:
        read_bounded_bytes("/proc/self/status", 10, "weights file")
    assert "holds more than the 10 bytes a weights file may be" in str(info.value)


def test_text_is_utf8_with_newlines_as_read_text_reads_them(tmp_path: Path) -> None:
    path = tmp_path / "t.md"
    path.write_bytes("é\r\nb\rc\n".encode())
    assert read_text(path, "system prompt", max_bytes=100) == path.read_text(encoding="utf-8")
    path.write_bytes(b"\xff")
    with pytest.raises(PromptError, match="the system prompt is not UTF-8 text"):
        read_text(path, "system prompt", PromptError, max_bytes=100)
    with pytest.raises(PromptError, match="cannot read the system prompt: No such file"):
        read_text(tmp_path / "none.md", "system prompt", PromptError, max_bytes=100)


def test_a_line_is_read_up_to_its_cap_and_a_longer_one_refused() -> None:
    text = io.StringIO("abc\nabcd\n" + "x" * 10**6)
    assert read_line(text, 3, "f:1", fix="fix") == "abc\n"
    with pytest.raises(AmuledError) as info:
        read_line(text, 3, "f:2", fix="fix")
    assert str(info.value) == (
        "f:2: a line longer than the 3 characters a line may be (it is not read whole); fix"
    )
    binary = io.BytesIO(b"abc")  # the last line, without a newline, at the cap
    assert read_line(binary, 3, "f:1", unit="bytes", fix="fix") == b"abc"
    assert read_line(binary, 3, "f:2", unit="bytes", fix="fix") == b""
