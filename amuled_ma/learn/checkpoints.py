"""Read checkpoints weights-only (never rsl-rl's ``OnPolicyRunner.load``) and write them atomically.

docs/trust.md: a failed write keeps the last checkpoint.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from amuled_ma.errors import CheckpointError
from amuled_ma.files.safe import (
    check_write_target,
    checked_read_path,
    failure_fix,
    fsync_folder,
    write_failure,
)
from amuled_ma.files.torch_load import load_weights_only


class CheckpointWriteError(CheckpointError):
    """A checkpoint could not be written (full disk, ...); the last one on disk is kept."""


#: Where else a checkpoint may go, said beside a full disk or a folder not writable.
RUN_DIR_ELSEWHERE = "write into another --run-dir"

#: Name of the newest checkpoint in a variant folder.
LAST = "model_last.pt"

#: Keys every job's checkpoint holds (``learn.population`` writes them).
TRAINER_KEYS = ("actor_state_dict", "critic_state_dict", "optimizer_state_dict", "iter", "infos")


def read_checkpoint(path: str | Path, *, need: Iterable[str] = ("actor_state_dict",)) -> dict:
    """Load a checkpoint as plain data (``weights_only=True``) holding every key in ``need``.

    Raises:
        CheckpointError: The file is missing, not a weights-only checkpoint (nothing from
            it was run), not a dict, or lacks a key in ``need``.
        UnsafePathError: The file is a symbolic link or not a regular file; nothing is read.
    """
    path = checked_read_path(Path(path).parent, Path(path).name)
    try:
        state = load_weights_only(path, "checkpoint")
    except CheckpointError as error:
        if not path.is_file():
            raise
        raise CheckpointError(
            f"{error}; retrain it (--force), or convert a checkpoint you trust to plain "
            "tensors and numbers"
        ) from error.__cause__
    if not isinstance(state, dict):
        raise CheckpointError(
            f"cannot load checkpoint {path}: expected a dict of state dicts, found "
            f"{type(state).__name__}; retrain it with --force"
        )
    missing = [key for key in need if key not in state]
    if missing:
        raise CheckpointError(
            f"checkpoint {path} lacks {', '.join(repr(k) for k in missing)} (found keys: "
            f"{', '.join(sorted(map(str, state))) or 'none'}); it was not written by amuled, "
            "or is damaged: retrain it with --force"
        )
    return state


def checkpoint_infos(path: str | Path) -> dict[str, Any] | None:
    """Return a checkpoint's ``infos`` (our book-keeping), None when there is no file.

    Raises CheckpointError: the file exists but cannot be read safely.
    """
    path = Path(path)
    if not path.is_file():
        return None
    infos = read_checkpoint(path, need=()).get("infos")
    return infos if isinstance(infos, dict) else {}


def write_checkpoints(writes: Sequence[tuple[Path, Callable[[str], Any]]]) -> list[Path]:
    """Write ``(path, write(temp))`` checkpoints as one set: old files stay until all are whole.

    Raises:
        CheckpointWriteError: A write failed (the message names the file, the cause and the
            fix); every temporary file is removed, every old kept.
        UnsafePathError: A path is a link or not a regular file; nothing was written.
    """
    temps: list[tuple[str, Path]] = []
    path = Path()
    try:
        for path, write in writes:
            path = check_write_target(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
            os.close(fd)
            temps.append((tmp, path))
            write(tmp)
            with open(tmp, "rb+") as handle:
                os.fsync(handle.fileno())
        while temps:
            tmp, path = temps[0]
            os.replace(tmp, path)
            temps.pop(0)
    except (OSError, RuntimeError) as error:
        raise CheckpointWriteError(_write_failure(path, error)) from error
    finally:
        for tmp, _ in temps:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    done = [Path(path) for path, _ in writes]
    for folder in dict.fromkeys(path.parent for path in done):
        fsync_folder(folder)
    return done


def _disk_full(folder: Path, *, margin: int = 1 << 20) -> bool:
    """Whether the file system of ``folder`` has less than ``margin`` bytes left."""
    try:
        stats = os.statvfs(folder)
    except OSError:
        return False
    return stats.f_bavail * stats.f_frsize < margin


def _write_failure(path: Path, error: BaseException) -> str:
    """The one line of a checkpoint that could not be written."""
    if isinstance(error, OSError):
        cause = error
    elif _disk_full(path.parent):
        # torch's zip writer names no cause ("unexpected pos 128 vs 0"): the disk says it
        cause = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    else:
        cause = OSError(str(error))
    then = "resume" if cause.errno in (errno.EACCES, errno.EPERM, errno.EROFS) else None
    kept = (
        f"the last checkpoint {path} is kept" if path.is_file() else "no earlier checkpoint exists"
    )
    return write_failure(
        path,
        cause,
        failure_fix(cause.errno, then or "resume with --resume", elsewhere=RUN_DIR_ELSEWHERE),
        kept=kept,
        what="checkpoint ",
    )
