"""Every option the README and docs/ give an ``amuled`` command is one that command takes.

Each ``amuled COMMAND [SUB] ... --flag`` in README.md and docs/*.md (inline code and code
blocks) is checked against the command's own ``--help``: a renamed or removed option in the
tool fails here, naming the page, the command and the option.
"""

from __future__ import annotations

import functools
import re

import pytest
from tiny_cli import REPO

from amuled_ma.cli import main

PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
#: ``amuled`` then one or two lower-case words, then the rest of the command up to a
#: closing backtick, a table bar or the end of the line.
COMMAND = re.compile(r"amuled ((?:[a-z][a-z-]* ?){1,2})([^`\n|#]*)")
FLAG = re.compile(r"(?<![\w-])(--[a-z][a-z-]*)")


@functools.cache
def help_text(*words: str) -> str | None:
    """The ``--help`` of ``amuled WORDS`` (None when the words name no command)."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([*words, "--help"])
        except SystemExit as stop:
            if stop.code != 0:
                return None
    return out.getvalue()


def _uses() -> list[tuple[str, tuple[str, ...], str]]:
    """(page, command words, flag) of every option written after an ``amuled`` command."""
    top = help_text()
    assert top is not None
    found = []
    for page in PAGES:
        for line in page.read_text(encoding="utf-8").splitlines():
            for match in COMMAND.finditer(line):
                words = tuple(match.group(1).split())
                if not words or not re.search(rf"^    {re.escape(words[0])}\b", top, re.M):
                    continue  # prose ("amuled writes ..."), not a command
                rest = match.group(2)
                if len(words) == 2 and help_text(*words) is None:
                    words, rest = words[:1], f"{words[1]} {rest}"
                for flag in FLAG.findall(rest):
                    found.append((page.name, words, flag))
    return sorted(set(found))


def test_the_pages_name_commands_with_options():
    uses = _uses()
    assert len(uses) > 50  # the pattern finds the commands (it is not vacuous)
    assert ("README.md", ("run", "findmilk"), "--quick") in uses


@pytest.mark.parametrize(("page", "words", "flag"), _uses())
def test_every_option_in_the_docs_is_the_commands(page: str, words: tuple[str, ...], flag: str):
    text = help_text(*words) or ""
    top = help_text() or ""
    assert re.search(rf"(?<![\w-]){re.escape(flag)}\b", text + top), (
        f"{page}: 'amuled {' '.join(words)}' has no option {flag}"
    )
