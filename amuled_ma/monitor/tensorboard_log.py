"""TensorBoard scalars whose failed write is one line naming the folder, not a thread's traceback.

``SummaryWriter``'s thread's ``OSError`` is silenced by an ``excepthook``; the next call raises.
"""

from __future__ import annotations

import contextlib
import threading
from pathlib import Path

from amuled_ma.files.safe import FileWriteError, write_failure

_hook_lock = threading.Lock()
_previous_hook = threading.excepthook


def _quiet_hook(args: threading.ExceptHookArgs) -> None:
    """``threading.excepthook``: silent for an ``OSError`` ending a TensorBoard thread."""
    thread_module = type(args.thread).__module__ if args.thread is not None else ""
    if issubclass(args.exc_type, OSError) and thread_module.startswith("tensorboard."):
        return  # the writer raises it again in the caller: one line there
    _previous_hook(args)


class TensorBoardLog:
    """A ``SummaryWriter`` for scalars; a failed write (``failed``) raises FileWriteError."""

    def __init__(self, log_dir: str | Path, *, flush_secs: float = 30) -> None:
        from torch.utils.tensorboard import SummaryWriter

        global _previous_hook
        with _hook_lock:  # put _quiet_hook in front of the process's hook, once
            if threading.excepthook is not _quiet_hook:
                _previous_hook = threading.excepthook
                threading.excepthook = _quiet_hook
        self.log_dir = Path(log_dir)
        self.failed = False
        try:
            self._writer = SummaryWriter(log_dir=str(self.log_dir), flush_secs=flush_secs)
        except OSError as error:
            raise self._failure(error) from error

    def _failure(self, error: OSError) -> FileWriteError:
        self.failed = True
        return FileWriteError(
            write_failure(
                f"TensorBoard events in {self.log_dir}",
                error,
                kept="the events written before are kept",
                fix=(
                    "free some disk space, then resume (or set [output] tensorboard = false: "
                    "curve.json holds the same numbers)"
                ),
            )
        )

    def add_scalar(self, key: str, value: float, step: int) -> None:
        """Queue one scalar; FileWriteError when TensorBoard's thread failed an earlier event."""
        try:
            self._writer.add_scalar(key, value, step)
        except OSError as error:
            raise self._failure(error) from error

    def close(self) -> None:
        """Write every queued event and close the file (after a raised failure: only close).

        Raises:
            FileWriteError: An event could not be written; the file is closed all the same.
        """
        try:
            if not self.failed:
                self._writer.flush()
        except OSError as error:
            raise self._failure(error) from error
        finally:
            with contextlib.suppress(OSError):
                self._writer.close()
