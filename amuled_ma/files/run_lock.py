"""One writer per run folder: an advisory ``fcntl.flock`` held while a command writes.

Not ``filelock``: the kernel releases ``flock`` when the holder dies (``kill -9`` too), and the
message names the holder's pid and command. Local to one machine; re-entrant in one process.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from amuled_ma.errors import AmuledError

#: Name of the lock file inside a run folder.
LOCK_NAME = ".amuled.lock"

#: Folders this process holds, with how many nested holds each has, and their open files.
_HELD: dict[Path, tuple[int, int]] = {}


class RunFolderBusy(AmuledError, RuntimeError):
    """Another process is writing into the run folder."""


def _holder(fd: int) -> str:
    """Describe the lock's current holder from the file's content."""
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = json.loads(os.read(fd, 65536).decode("utf-8") or "{}")
        return f"pid {data['pid']}, since {data['since']}: {data['command']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that has not yet written its name"


@contextlib.contextmanager
def run_folder_lock(folder: str | Path, command: str | None = None) -> Iterator[Path]:
    """Hold the write lock of a run folder (created if needed); yields the lock's path.

    ``command`` is recorded for other writers (default: ``sys.argv``).

    Raises:
        RunFolderBusy: Another process holds it (named by pid, start time and command).
        AmuledError: The folder cannot be created or the lock file cannot be written.
    """
    folder = Path(folder)
    # the folders made here, deepest first: removed again if the command fails and leaves nothing
    made = list(itertools.takewhile(lambda p: not p.exists(), [folder, *folder.parents]))
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise AmuledError(
            f"cannot create the run folder {folder}: {error.strerror or error}; choose "
            "another --run-dir (or [output].runs_dir) you can write to"
        ) from error
    key = folder.resolve()
    path = key / LOCK_NAME
    if key in _HELD:
        fd, count = _HELD[key]
        _HELD[key] = (fd, count + 1)
        try:
            yield path
        finally:
            fd, count = _HELD[key]
            _HELD[key] = (fd, count - 1)
        return
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as error:
        raise AmuledError(
            f"cannot write the lock file {path}: {error.strerror or error}; the run folder "
            "must be writable (choose another --run-dir)"
        ) from error
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunFolderBusy(
                f"{folder} is being written by another amuled process ({_holder(fd)}); wait "
                "for it to finish or stop it, or write into another --run-dir"
            ) from None
        record = {
            "pid": os.getpid(),
            "since": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": command or " ".join(["amuled", *sys.argv[1:]]),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode("utf-8"), 0)
        _HELD[key] = (fd, 1)
        try:
            yield path
        except BaseException:
            with contextlib.suppress(OSError):  # a failed command leaves no empty run folder
                if made and all(p.name == LOCK_NAME for p in made[0].iterdir()):
                    path.unlink()
                    for made_folder in made:
                        made_folder.rmdir()
            raise
        finally:
            del _HELD[key]
    finally:
        os.close(fd)  # closing the last descriptor releases the flock
