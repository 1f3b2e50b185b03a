"""Locate the data that ships with the package: ``prompts/`` and ``scenarios/``.

An installed wheel carries them under ``amuled_ma/_data/``; a source checkout
(editable install) keeps them at the repository's top level. Both are found from
this file's location, never from the current working directory.
"""

from __future__ import annotations

from pathlib import Path

_PACKAGE_DIR = Path(__file__).resolve().parent


def data_dir(name: str) -> Path:
    """Return the directory of a shipped data folder.

    Args:
        name: ``"prompts"`` or ``"scenarios"``.

    Returns:
        The existing directory holding that data.

    Raises:
        FileNotFoundError: Neither the installed nor the source-tree location exists.
    """
    for candidate in (_PACKAGE_DIR / "_data" / name, _PACKAGE_DIR.parent / name):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        f"amuled-ma data folder {name!r} not found under {_PACKAGE_DIR / '_data'} "
        f"or {_PACKAGE_DIR.parent}; reinstall the package"
    )


def prompts_dir() -> Path:
    """Return the shipped ``prompts/`` directory."""
    return data_dir("prompts")


def scenarios_dir() -> Path:
    """Return the shipped ``scenarios/`` directory."""
    return data_dir("scenarios")
