"""Files written whole and never through a link; run-folder files read only when regular and inside.

A link in a run folder someone hands over could make a report quote any file (docs/trust.md).
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any, Literal, overload

from amuled_ma.errors import AmuledError


class UnsafePathError(AmuledError, ValueError):
    """A path to write is not a regular file, or a file to read is a link or leaves its folder."""


class FileWriteError(AmuledError, OSError):
    """A file could not be written (a full disk); the old file is kept. An OSError too."""


#: ``st_mode`` file types, in words, for the refusals.
_KINDS = (
    (stat.S_ISLNK, "a symbolic link"),
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
)


def file_kind(path: Path, mode: int) -> str:
    """What a non-regular file is, in words (a link says where it points)."""
    for test, words in _KINDS:
        if test(mode):
            if words == "a symbolic link":
                with contextlib.suppress(OSError):
                    return f"{words} (to {os.readlink(path)})"
            return words
    return "not a regular file"


def check_write_target(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` (absent or a regular file); follows no link.

    Raises:
        UnsafePathError: ``path`` is a link, a device, a FIFO, a socket or a folder.
        OSError: ``path`` cannot be examined.
    """
    path = Path(path)
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return path
    if stat.S_ISREG(mode):
        return path
    raise _not_regular(path, mode)


def _not_regular(path: Path, mode: int) -> UnsafePathError:
    """The refusal to write ``path``, a file of type ``mode`` that is not regular."""
    if stat.S_ISLNK(mode):
        fix = "remove the link (a new file is then written in its place), or write elsewhere"
    elif stat.S_ISDIR(mode):
        fix = "give the path of a file, not a folder"
    else:
        fix = "give the path of a new or a regular file"
    return UnsafePathError(
        f"{path}: is {file_kind(path, mode)}, not a regular file; amuled writes only regular "
        f"files and never through a link; nothing was written; {fix}"
    )


def check_write_targets(paths: Iterable[str | os.PathLike[str]]) -> None:
    """:func:`check_write_target` on each path, before any work that would end in writing them."""
    for path in paths:
        check_write_target(path)


def check_own_folder(folder: Path, why: str) -> None:
    """Refuse (UnsafePathError, ending ``why``) a link, or an existing ``folder`` not a folder."""
    if folder.is_symlink() or (os.path.lexists(folder) and not folder.is_dir()):
        kind = f"a symbolic link (to {os.readlink(folder)})" if folder.is_symlink() else "a file"
        raise UnsafePathError(f"{folder}: is {kind}, not a folder; {why}")


def failure_fix(code: int | None, then: str, *, elsewhere: str | None = None) -> str:
    """What to do about a write that failed with ``errno`` ``code`` (``elsewhere``: an aside)."""
    aside = f" (or {elsewhere})" if elsewhere else ""
    if code in (errno.ENOSPC, errno.EDQUOT):
        return f"free some disk space{aside}, then {then}"
    if code == errno.EFBIG:
        return f"raise the file-size limit (ulimit -f), then {then}"
    if code in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"make the folder writable{aside}, then {then}"
    return f"check the folder and the disk, then {then}"


def write_failure(
    path: Path | str,
    error: OSError,
    fix: str | None = None,
    *,
    kept: str | None = None,
    what: str = "",
) -> str:
    """The line ``"cannot write WHAT PATH: WHY; KEPT; FIX"`` (``fix``: :func:`failure_fix`'s)."""
    why = " ".join((error.strerror or str(error)).split())[:200]
    if fix is None:
        fix = failure_fix(error.errno, "run the command again")
    if kept is None:
        kept = "the old file is kept" if Path(path).is_file() else "nothing was written"
    return f"cannot write {what}{path}: {why}; {kept}; {fix}"


def fsync_folder(folder: Path) -> None:
    """Flush a folder's entries (the rename) to disk; a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


@overload
def atomic_writer(
    path: str | os.PathLike[str],
    *,
    text: Literal[False] = ...,
    encoding: str = ...,
    newline: str | None = ...,
    fix: str | None = ...,
) -> contextlib.AbstractContextManager[IO[bytes]]: ...
@overload
def atomic_writer(
    path: str | os.PathLike[str],
    *,
    text: Literal[True],
    encoding: str = ...,
    newline: str | None = ...,
    fix: str | None = ...,
) -> contextlib.AbstractContextManager[IO[str]]: ...
@contextlib.contextmanager
def atomic_writer(
    path: str | os.PathLike[str],
    *,
    text: bool = False,
    encoding: str = "utf-8",
    newline: str | None = None,
    fix: str | None = None,
) -> Iterator[IO[Any]]:
    """A file object (``text``: as :func:`open`) whose contents replace ``path`` at the block's end.

    The target is checked (:func:`check_write_target`) before and after; the temporary file is
    flushed to disk before it is renamed over ``path``. ``fix``: as :func:`write_failure`.

    Raises:
        UnsafePathError: ``path`` is not absent nor a regular file; nothing was written.
        FileWriteError: Writing, flushing or renaming failed (an ``OSError`` in the block
            too); ``path`` is as it was and no temporary file is left.
    """
    path = check_write_target(path)
    tmp: Path | None = None
    try:
        # a new .NAME.RANDOM.tmp beside path, of the target's mode; O_EXCL with O_NOFOLLOW
        # never opens anything that exists, a link included
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
        while tmp is None:
            candidate = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
            with contextlib.suppress(FileExistsError):
                fd = os.open(candidate, flags, 0o666)
                tmp = candidate
        with contextlib.suppress(OSError):
            os.fchmod(fd, stat.S_IMODE(os.stat(path, follow_symlinks=False).st_mode))
        handle: IO[bytes] | IO[str]
        if text:
            handle = os.fdopen(fd, "w", encoding=encoding, newline=newline)
        else:
            handle = os.fdopen(fd, "wb")
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        check_write_target(path)
        os.replace(tmp, path)
        tmp = None
        fsync_folder(path.parent)
    except UnsafePathError:
        raise
    except OSError as error:
        raise FileWriteError(write_failure(path, error, fix)) from error
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def write_bytes_atomic(
    path: str | os.PathLike[str], data: bytes, *, fix: str | None = None
) -> Path:
    """Write ``data`` as the whole of ``path`` through :func:`atomic_writer`; returns ``path``."""
    with atomic_writer(path, fix=fix) as handle:
        handle.write(data)
    return Path(path)


def write_text_atomic(
    path: str | os.PathLike[str],
    text: str,
    *,
    encoding: str = "utf-8",
    fix: str | None = None,
) -> Path:
    """Write ``text`` as the whole of ``path`` through :func:`atomic_writer`; returns ``path``."""
    with atomic_writer(path, text=True, encoding=encoding, newline="", fix=fix) as handle:
        handle.write(text)
    return Path(path)


def append_text(path: str | os.PathLike[str], text: str, *, fix: str | None = None) -> Path:
    """Append ``text`` (UTF-8) to ``path``, creating it; never through a link; returns ``path``.

    Raises:
        UnsafePathError: ``path`` is not absent nor a regular file; nothing was written.
        FileWriteError: The write failed (a full disk): one line naming ``path``.
    """
    path = check_write_target(path)
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as error:
        if error.errno in (errno.ELOOP, errno.ENXIO):  # a link, a FIFO put there meanwhile
            check_write_target(path)
        raise FileWriteError(write_failure(path, error, fix, kept="nothing was written")) from error
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):  # put there between the check and the open
            raise _not_regular(path, mode)
        with os.fdopen(fd, "ab", closefd=False) as handle:
            handle.write(text.encode("utf-8"))
            handle.flush()
    except OSError as error:
        raise FileWriteError(
            write_failure(path, error, fix, kept="what was written before is kept")
        ) from error
    finally:
        os.close(fd)
    return path


def checked_read_path(folder: str | os.PathLike[str], name: str | os.PathLike[str]) -> Path:
    """``folder / name`` (maybe missing), refused if reading it follows a link or leaves ``folder``.

    Raises:
        UnsafePathError: A symbolic link, not a regular file, or outside ``folder``.
        OSError: It cannot be examined.
    """
    folder = Path(folder)
    path = folder / name
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return path
    if stat.S_ISLNK(mode):
        raise UnsafePathError(
            f"{path}: is {file_kind(path, mode)}; amuled does not follow links in a run folder; "
            "put the file itself there (cp --remove-destination TARGET LINK) or remove the link"
        )
    if not stat.S_ISREG(mode):
        raise UnsafePathError(
            f"{path}: is {file_kind(path, mode)}, not a regular file; it is not read; remove it, "
            "is it the right folder?"
        )
    real, base = path.resolve(), folder.resolve()
    if not real.is_relative_to(base):
        raise UnsafePathError(
            f"{path}: resolves to {real}, outside its folder {base}; it is not read; put the "
            "file itself in the folder"
        )
    return path
