"""A full disk under TensorBoard's writer: one line naming the folder, no thread traceback.

The disk is real: a 16 KiB tmpfs (root only; skipped with the reason otherwise). The plain
``SummaryWriter``, under Python's own ``threading.excepthook``, is run on the same kind of
disk: its writer thread prints a traceback naming no file, which :class:`TensorBoardLog`
removes.
"""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from small_disk import small_disk

from amuled_ma.files.safe import FileWriteError
from amuled_ma.monitor.tensorboard_log import TensorBoardLog

#: Scalars written until the disk is full (about 50 bytes each: ten times 16 KiB).
SCALARS = 3_000


def fill_log(log: TensorBoardLog) -> None:
    for i in range(SCALARS):
        log.add_scalar("loss", float(i), i)
    log.close()


def test_the_plain_writer_thread_prints_a_traceback(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from torch.utils.tensorboard import SummaryWriter

    monkeypatch.setattr(threading, "excepthook", threading.__excepthook__)  # Python's own
    with small_disk(tmp_path, "16k") as disk:
        writer = SummaryWriter(log_dir=str(disk / "tb"), flush_secs=0)
        with pytest.raises(OSError, match="No space left on device") as caught:
            for i in range(SCALARS):
                writer.add_scalar("loss", float(i), i)
    assert caught.value.filename is None  # the caller's error names no file
    err = capfd.readouterr().err
    assert "Exception in thread" in err and "Traceback" in err, err
    assert str(disk) not in err


def test_a_full_disk_is_one_line_naming_the_folder(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[BaseException | None] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: seen.append(args.exc_value))
    with small_disk(tmp_path, "16k") as disk:
        log = TensorBoardLog(disk / "tb", flush_secs=0)
        with pytest.raises(FileWriteError) as caught:
            fill_log(log)
        assert log.failed
        log.close()  # after the failure was raised: closes, raises nothing more
    line = str(caught.value)
    assert "\n" not in line
    assert line.startswith(f"cannot write TensorBoard events in {disk / 'tb'}: ")
    assert "No space left on device" in line and "free some disk space" in line
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception in thread" not in err, err
    assert seen == []  # the writer thread's error went to no other hook


def test_other_threads_errors_go_to_the_hook_before(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[BaseException | None] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: seen.append(args.exc_value))
    TensorBoardLog(tmp_path / "tb").close()  # installs its hook in front
    thread = threading.Thread(target=lambda: Path("/nonexistent/amuled-test").read_bytes())
    thread.start()
    thread.join()
    assert [type(e) for e in seen] == [FileNotFoundError]
