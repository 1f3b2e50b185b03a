"""The SHA-256 of a file's bytes: the identity of an input (a recording, an imported policy)."""

from __future__ import annotations

import hashlib
from pathlib import Path


def sha256_file(path: str | Path) -> str:
    """The hex SHA-256 of a file's bytes (``hashlib.file_digest``); OSError when unreadable."""
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()
