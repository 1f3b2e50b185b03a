"""The output folder of a benchmark: the one asked for, or a temporary one removed after."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def output_folder(out: Path | None, prefix: str) -> Iterator[Path]:
    """Yield ``out`` (created) or a temporary folder named ``prefix...`` (deleted after)."""
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        yield Path(out)
        return
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        yield Path(tmp)
