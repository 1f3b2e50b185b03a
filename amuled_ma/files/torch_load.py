"""Load a ``.pt`` file without running code from it (``torch.load(..., weights_only=True)``)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from amuled_ma.errors import CheckpointError
from amuled_ma.files.limits import check_size

#: Largest PyTorch file loaded whole [bytes, 1 GiB]: the shipped scenarios' are under 1 MB, and
#: 50 million float32 weights with Adam's two moments make 600 MB.
MAX_TORCH_FILE_BYTES = 2**30


def load_weights_only(path: str | Path, what: str = "checkpoint") -> Any:
    """``torch.load(path, map_location="cpu", weights_only=True)``; ``what`` names the file.

    Raises:
        CheckpointError: Missing, over :data:`MAX_TORCH_FILE_BYTES` (unread), needing a global
            (named; nothing ran), or not a readable PyTorch file.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{what} not found: {path}")
    check_size(
        path,
        MAX_TORCH_FILE_BYTES,
        "PyTorch file",
        error=CheckpointError,
        head=f"cannot load {what} {path}: it",
        note="those of the shipped scenarios are under 1 MB",
        fix="it is not a file amuled or the authors' CleanRL wrote",
    )
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a bad or unsafe file
        unsafe = re.search(r"GLOBAL ([\w.]+)", str(error))
        if unsafe:
            why = (
                f"it needs {unsafe.group(1)} to load, which could run code from the file "
                "(refused as not weights-only; nothing was run)"
            )
        else:
            detail = re.search(r"WeightsUnpickler error: \s*(.+)", str(error))
            first = (detail.group(1) if detail else str(error)).strip().splitlines()
            why = f"it is not a readable PyTorch file ({first[0] if first else error})"
        raise CheckpointError(f"cannot load {what} {path}: {why}") from error
