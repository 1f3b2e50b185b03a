"""The shipped ``prompts/`` and ``scenarios/``: in ``amuled_ma/_data/``, else the checkout's."""

from __future__ import annotations

from pathlib import Path

from amuled_ma.errors import AmuledError
from amuled_ma.files.limits import decode_text, read_bounded_bytes

_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # amuled_ma/

#: Largest prompt file read [bytes]: 100 times the shipped ones (at most 9,684 bytes); every
#: byte goes to the LLM with each request, so a larger file is a wrong file.
MAX_PROMPT_BYTES = 1_000_000


def data_dir(name: str) -> Path:
    """The shipped data folder ``name``; FileNotFoundError when neither location has it."""
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


def read_text(
    path: Path,
    what: str,
    error_class: type[Exception] | None = None,
    *,
    max_bytes: int,
    note: str = "",
) -> str:
    """A UTF-8 text file (`decode_text`); ``error_class`` over ``max_bytes`` or unreadable."""
    error = error_class or AmuledError
    try:
        data = read_bounded_bytes(path, max_bytes, what, error=error, note=note)
    except OSError as failure:
        if isinstance(failure, error):  # the refusal itself (an error class that is an OSError)
            raise
        raise error(
            f"{path}: cannot read the {what}: {failure.strerror or failure}; check the path"
        ) from failure
    return decode_text(path, data, what, error=error)
