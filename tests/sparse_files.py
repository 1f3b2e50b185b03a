"""Gigabyte files that take no disk and no time, for the tests of the size caps."""

from __future__ import annotations

import os
from pathlib import Path


def sparse(path: str | os.PathLike[str], size: int) -> Path:
    """Make ``path`` ``size`` bytes long, its new bytes zeros that use no disk (sparse).

    What the file held stays (a test may write a first line, then grow it); a missing
    file is created.

    Returns:
        The path.

    """
    with open(path, "ab") as handle:
        handle.truncate(size)
    return Path(path)
