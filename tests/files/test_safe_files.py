"""One rule for paths: writes follow no link and replace only regular files; reads stay inside.

Every refusal is one line naming the path; the file a link points to, a FIFO or a device
node is left exactly as it was (its bytes and its ``st_mode``, read with ``os.lstat``).
The full disk is real: a 64 KiB tmpfs (root only; skipped with the reason otherwise).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from small_disk import small_disk

from amuled_ma.files.safe import (
    FileWriteError,
    UnsafePathError,
    atomic_writer,
    check_write_target,
    checked_read_path,
    write_bytes_atomic,
    write_text_atomic,
)


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def one_line(error: pytest.ExceptionInfo[Exception]) -> str:
    line = str(error.value)
    assert "\n" not in line
    return line


def test_a_new_file_and_a_regular_file_are_written_whole(tmp_path: Path) -> None:
    path = tmp_path / "report.md"
    write_text_atomic(path, "first é\n")
    assert path.read_bytes() == "first é\n".encode()
    os.chmod(path, 0o600)
    write_bytes_atomic(path, b"second")
    assert path.read_bytes() == b"second"
    assert stat.S_IMODE(os.lstat(path).st_mode) == 0o600  # the owner's choice is kept
    assert leftovers(tmp_path) == []


def test_a_link_in_the_target_place_is_refused_and_its_file_untouched(tmp_path: Path) -> None:
    outside = tmp_path / "outside.txt"
    outside.write_bytes(b"keep me")
    link = tmp_path / "run" / "results.json"
    link.parent.mkdir()
    link.symlink_to(outside)
    with pytest.raises(UnsafePathError) as caught:
        write_text_atomic(link, "{}")
    line = one_line(caught)
    assert str(link) in line and f"a symbolic link (to {outside})" in line
    assert "remove the link" in line
    assert outside.read_bytes() == b"keep me"
    assert os.path.islink(link)
    assert leftovers(link.parent) == []


def test_a_dangling_link_is_refused_and_nothing_is_created(tmp_path: Path) -> None:
    link = tmp_path / "metrics_greedy.png"
    link.symlink_to(tmp_path / "made-through-the-link.png")
    with pytest.raises(UnsafePathError), atomic_writer(link) as handle:
        handle.write(b"png")
    assert not (tmp_path / "made-through-the-link.png").exists()


def test_a_fifo_and_a_folder_are_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "page.html"
    os.mkfifo(fifo)
    with pytest.raises(UnsafePathError) as caught:
        write_text_atomic(fifo, "<html>")
    assert "a FIFO (named pipe)" in one_line(caught)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    with pytest.raises(UnsafePathError) as caught:
        check_write_target(tmp_path)
    assert "a folder" in one_line(caught)


def test_a_device_node_is_refused_and_stays_a_device(tmp_path: Path) -> None:
    if os.geteuid() != 0:
        pytest.skip("making a device node needs root")
    full = tmp_path / "full"
    os.mknod(full, stat.S_IFCHR | 0o666, os.makedev(1, 7))  # the node /dev/full is
    before = os.lstat(full)
    with pytest.raises(UnsafePathError) as caught:
        write_text_atomic(full, "<html>")
    assert f"{full}: is a character device" in one_line(caught)
    after = os.lstat(full)
    assert (after.st_mode, after.st_rdev) == (before.st_mode, before.st_rdev)


def test_a_full_disk_names_the_file_keeps_the_old_one_and_leaves_no_temp(
    tmp_path: Path,
) -> None:
    with small_disk(tmp_path, "64k") as disk:
        path = disk / "results.json"
        write_text_atomic(path, "old")
        with pytest.raises(FileWriteError) as caught:
            write_bytes_atomic(path, b"x" * (256 * 1024))  # four times the disk
        line = one_line(caught)
        assert line.startswith(f"cannot write {path}: No space left on device")
        assert "the old file is kept" in line and "free some disk space" in line
        assert path.read_text() == "old"
        assert leftovers(disk) == []


def test_an_error_inside_the_block_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    path.write_text("old")
    with pytest.raises(ZeroDivisionError), atomic_writer(path, text=True) as handle:
        handle.write("half")
        _ = 1 / 0
    assert path.read_text() == "old"
    assert leftovers(tmp_path) == []


def test_reads_refuse_a_link_a_fifo_and_a_way_out(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "base").mkdir(parents=True)
    secret = tmp_path / "secret.json"
    secret.write_text("{}")
    (run / "base" / "curve.json").write_text("[]")
    assert checked_read_path(run, "base/curve.json") == run / "base" / "curve.json"
    assert checked_read_path(run, "absent.json") == run / "absent.json"

    (run / "results.json").symlink_to(secret)
    with pytest.raises(UnsafePathError) as caught:
        checked_read_path(run, "results.json")
    assert "does not follow links in a run folder" in one_line(caught)

    os.mkfifo(run / "report.md")
    with pytest.raises(UnsafePathError) as caught:
        checked_read_path(run, "report.md")
    assert "a FIFO" in one_line(caught)

    with pytest.raises(UnsafePathError) as caught:
        checked_read_path(run, "../secret.json")
    assert "outside its folder" in one_line(caught)

    (run / "linked").symlink_to(tmp_path)  # a linked folder: the file itself is regular
    with pytest.raises(UnsafePathError) as caught:
        checked_read_path(run, "linked/secret.json")
    assert f"resolves to {secret.resolve()}" in one_line(caught)


def test_a_demonstrator_table_is_written_whole_and_not_through_a_link(tmp_path: Path) -> None:
    import torch

    from amuled_ma.tasks.demonstrators.table import DemonstratorBelief

    counts = torch.tensor([[3, 1, 0, 0], [0, 0, 2, 2]])
    table = DemonstratorBelief("findmilk", torch.tensor([5, 9]), counts, {"episodes": 2})
    path = table.save(tmp_path / "findmilk.npz")
    back = DemonstratorBelief.load(path, expect={"episodes": 2})
    assert back.states.tolist() == [5, 9] and back.counts.tolist() == counts.tolist()
    outside = tmp_path / "outside.npz"
    outside.write_bytes(b"kept")
    (tmp_path / "linked.npz").symlink_to(outside)
    with pytest.raises(UnsafePathError):
        table.save(tmp_path / "linked.npz")
    assert outside.read_bytes() == b"kept"
