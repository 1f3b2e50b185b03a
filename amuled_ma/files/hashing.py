"""The SHA-256 of a file's bytes: the identity of an input (a recording, an imported policy)."""

from __future__ import annotations

import hashlib
from pathlib import Path


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file's bytes, read in blocks of 1 MiB.

    Args:
        path: The file.

    Returns:
        The hex digest.

    Raises:
        OSError: The file cannot be read.

    """
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
