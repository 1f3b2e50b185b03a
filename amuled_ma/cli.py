"""The ``amuled`` command line: discovers and dispatches `amuled_ma.commands`' ``register``."""

from __future__ import annotations

import argparse
import errno
import os
import re
import signal
import sys
import threading
import traceback
from collections.abc import Sequence
from typing import NoReturn

from amuled_ma import __version__, commands
from amuled_ma.clusters.plugins import set_allowed_plugins
from amuled_ma.errors import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_REFUSED,
    EXIT_TERMINATED,
    EXIT_USAGE,
    AmuledError,
    Terminated,
    TerminatedWhileStarting,
)
from amuled_ma.experiments.third_party_log import third_party_to_log

#: The exit statuses, as ``amuled --help`` and docs/trust.md list them.
EXIT_CODES_HELP = (
    "exit status: "
    f"{EXIT_OK} done; "
    f"{EXIT_REFUSED} an input or a run refused (one line 'amuled: error: ...'); "
    f"{EXIT_USAGE} a usage error (an unknown option, a missing argument); "
    f"{EXIT_INTERRUPTED} interrupted (Ctrl-C); "
    f"{EXIT_TERMINATED} terminated (SIGTERM)"
)


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line: what, where and the fix."""

    def error(self, message: str) -> NoReturn:
        """Print ``amuled: error: ...`` naming the command's ``--help``, exit with 2."""
        self.exit(EXIT_USAGE, f"amuled: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every discovered command."""
    parser = OneLineParser(
        prog="amuled",
        description=(
            "Ethical fine-tuning of RL agents with fused feedback from LLM moral clusters "
            "(AMULED). Run 'amuled COMMAND --help' for a command's options."
        ),
        epilog=EXIT_CODES_HELP,
    )
    parser.add_argument("--version", action="version", version=f"amuled-ma {__version__}")
    parser.add_argument(
        "--debug",
        action="store_true",
        help="on an error, print the Python traceback as well as the one-line message",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for _, module in commands.public_modules(commands):
        module.register(subparsers)
    return parser


def describe_os_error(error: OSError) -> str:
    """One line for a failed file or network operation: what, which path, and the fix."""
    where = error.filename if error.filename is not None else ""
    if error.filename2 is not None:
        where = f"{where} -> {error.filename2}"
    what = error.strerror or str(error)
    fixes = {
        errno.ENOSPC: "free some disk space, or write into another --run-dir",
        errno.EDQUOT: "free some disk space, or write into another --run-dir",
        errno.EROFS: "the file system is read-only: write into another --run-dir",
        errno.EACCES: "check the permissions, or write into another --run-dir",
        errno.EPERM: "check the permissions, or write into another --run-dir",
        errno.ENOENT: "check the path",
        errno.EISDIR: "give a file, not a folder",
        errno.ENOTDIR: "a part of the path is a file, not a folder",
    }
    fix = fixes.get(error.errno or -1, "check the path")
    return f"{where}: {what}; {fix}" if where else f"{what}; {fix}"


def one_line(text: str) -> str:
    """``text`` as one line: its non-blank lines, stripped of indentation and ``- `` bullets.

    A line ending with ``:`` runs into the next with a space; the others join with ``"; "``.
    """
    parts = [re.sub(r"^- +", "", line.strip()) for line in text.splitlines()]
    joined = ""
    for part in filter(None, parts):
        if joined:
            joined += " " if joined.endswith(":") else "; "
        joined += part
    return joined


def _raise_terminated(signum: int, _frame: object) -> None:
    raise Terminated(signum)


class _SignalsNotLost:
    """While a command runs: a Ctrl-C or SIGTERM whose exception Python drops is sent again.

    A handler run in a finalizer (``__del__``) has its exception dropped ("Exception ignored
    in ..."); a timer thread sends the signal again 0.1 s later, after this hook has returned.
    """

    def __enter__(self) -> None:
        self.previous = sys.unraisablehook
        sys.unraisablehook = self._send_again

    def __exit__(self, *_exc: object) -> None:
        sys.unraisablehook = self.previous

    def _send_again(self, unraisable: sys.UnraisableHookArgs) -> None:
        error = unraisable.exc_value
        if isinstance(error, KeyboardInterrupt):  # Terminated is one too
            number = signal.SIGTERM if isinstance(error, Terminated) else signal.SIGINT
            again = threading.Timer(0.1, os.kill, args=(os.getpid(), number))
            again.daemon = True
            again.start()
        else:
            self.previous(unraisable)


#: What a command may raise that the command line reports as one line and an exit status.
FAILURES = (KeyboardInterrupt, AmuledError, OSError, UnicodeDecodeError)


def report_failure(error: BaseException, *, debug: bool = False) -> int:
    """Print the one line of a failed command (one of `FAILURES`); return its exit status.

    Call it inside the ``except`` block; ``debug`` prints the traceback being handled first
    (not for Ctrl-C or SIGTERM).
    """
    if isinstance(error, Terminated):
        print("amuled: terminated (SIGTERM)", file=sys.stderr)
        return error.exit_code
    if isinstance(error, KeyboardInterrupt):
        print("amuled: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if debug:
        traceback.print_exc()
    if isinstance(error, AmuledError):
        text = str(error)
    elif isinstance(error, UnicodeDecodeError):
        text = (
            f"a file is not UTF-8 text ({error.reason} at byte {error.start}); save it as "
            "UTF-8 (run with --debug to see which read failed)"
        )
    elif isinstance(error, OSError):
        text = describe_os_error(error)
    else:
        raise TypeError(f"report_failure: not a command failure: {error!r}") from error
    print(f"amuled: error: {one_line(text)}", file=sys.stderr)
    return getattr(error, "exit_code", EXIT_REFUSED)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``amuled`` command line and return its exit status (:data:`EXIT_CODES_HELP`).

    Every expected failure prints one line ``amuled: error: <what, where, fix>`` (``--debug``:
    with the traceback); SIGTERM is handled like Ctrl-C. ``argv`` None reads ``sys.argv``: this
    process's own command line, which a SIGTERM while Ray starts ends at once after its line.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return EXIT_USAGE
    # code a data file names is imported only if this command line allowed it
    set_allowed_plugins(getattr(args, "allow_plugin", None) or ())
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        with third_party_to_log(), _SignalsNotLost():
            return int(args.handler(args) or EXIT_OK)
    except FAILURES as error:
        code = report_failure(error, debug=args.debug)
        if argv is None and isinstance(error, TerminatedWhileStarting):
            # this process's own command line: end it now, past the interpreter's exit,
            # which may hang or crash in what ray.init left half-built
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
        return code
    finally:
        signal.signal(signal.SIGTERM, previous)
        sys.stdout.flush()


if __name__ == "__main__":
    sys.exit(main())
