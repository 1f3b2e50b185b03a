"""The files training writes and reads back go through the one path rule (``safe_files``).

A variant's ``config.json`` (``experiments.run_folder``), its checkpoint
(``learn.checkpoints``) and a distilled fine-tune's ``distill.json`` and
``distill-examples.jsonl`` (``distill.state``): a link in their place is refused on write
and on read with one line naming it, and the file it points to keeps its bytes.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from amuled_ma.distill.state import EXAMPLES_FILE, LEDGER_FILE, StateFiles
from amuled_ma.experiments.run_folder import CONFIG, read_record, write_record
from amuled_ma.files.safe import UnsafePathError, append_text
from amuled_ma.learn.checkpoints import LAST, read_checkpoint, write_checkpoints
from amuled_ma.records.run_record import RunRecord


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    path = tmp_path / "notes.txt"
    path.write_bytes(b"keep me")
    return path


def linked(folder: Path, name: str, target: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    link = folder / name
    link.symlink_to(target)
    return link


def refused(call, link: Path) -> str:
    with pytest.raises(UnsafePathError) as caught:
        call()
    line = str(caught.value)
    assert "\n" not in line and str(link) in line and "symbolic link" in line, line
    return line


def test_config_json_is_written_and_read_back_never_through_a_link(
    tmp_path: Path, outside: Path
) -> None:
    record = RunRecord.model_validate({"scenario": {}, "command": ["amuled"], "time": "t"})
    plain = tmp_path / "plain"
    write_record(plain, record)
    assert read_record(plain, checkpoint=False) == record
    link = linked(tmp_path / "run" / "base", CONFIG, outside)
    refused(lambda: write_record(link.parent, record), link)
    refused(lambda: read_record(link.parent, checkpoint=False), link)
    assert outside.read_bytes() == b"keep me"


def test_a_checkpoint_is_written_and_read_never_through_a_link(
    tmp_path: Path, outside: Path
) -> None:
    link = linked(tmp_path / "run" / "base", LAST, outside)
    refused(lambda: write_checkpoints([(link, lambda tmp: Path(tmp).write_bytes(b"x"))]), link)
    refused(lambda: read_checkpoint(link), link)
    assert outside.read_bytes() == b"keep me"
    assert [p.name for p in link.parent.iterdir()] == [LAST]  # no temporary file left


def test_the_distillation_state_is_written_and_read_never_through_a_link(
    tmp_path: Path, outside: Path
) -> None:
    folder = tmp_path / "run" / "finetune-distilled"
    ledger = linked(folder, LEDGER_FILE, outside)
    examples = linked(folder, EXAMPLES_FILE, outside)
    files = StateFiles(folder)
    refused(lambda: files.save({"x": 1}), ledger)
    refused(lambda: files.load(), ledger)
    refused(lambda: files.append([{"key": "0" * 32}]), examples)
    refused(lambda: files.read_examples(), examples)
    assert outside.read_bytes() == b"keep me"
    ledger.unlink()
    files.save({"x": 1})
    assert json.loads(ledger.read_text())["x"] == 1 and not ledger.is_symlink()


def test_append_text_appends_and_refuses_a_fifo_without_blocking(tmp_path: Path) -> None:
    path = tmp_path / "pairs.jsonl"
    append_text(path, "a\n")
    append_text(path, "b\n")
    assert path.read_text() == "a\nb\n"
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(UnsafePathError) as caught:
        append_text(fifo, "x\n")  # an open() for writing would wait for a reader
    assert f"{fifo}: is a FIFO" in str(caught.value)
