"""Load a ``.pt`` file without running code from it (``torch.load(..., weights_only=True)``).

PyTorch's restricted unpickler refuses any global besides tensors, numbers, strings and
builtin containers before anything runs (``docs/trust.md``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from amuled_ma.errors import CheckpointError
from amuled_ma.files.limits import check_size

#: Largest PyTorch file loaded [bytes, 1 GiB]. ``torch.load`` reads a file whole into
#: memory; our checkpoints hold the networks, their optimiser state and a few counters
#: (those of the shipped scenarios are under 1 MB, and a policy of 50 million float32 weights
#: with Adam's two moments is 600 MB), so a larger file is not one we wrote.
MAX_TORCH_FILE_BYTES = 2**30


def load_weights_only(path: str | Path, what: str = "checkpoint") -> Any:
    """``torch.load(path, map_location="cpu", weights_only=True)``, with a clear error.

    ``what`` names the file in the message (``"checkpoint"``, ``"policy file"``).

    Raises:
        CheckpointError: The file is missing, larger than :data:`MAX_TORCH_FILE_BYTES`
            (refused from its size, before it is read), needs a global to load (named;
            refused, so nothing from it ran), or is not a readable PyTorch file.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{what} not found: {path}")
    try:
        check_size(
            path,
            MAX_TORCH_FILE_BYTES,
            "PyTorch file",
            error=CheckpointError,
            head=f"cannot load {what} {path}: it",
            note="those of the shipped scenarios are under 1 MB",
            fix="it is not a file amuled or the authors' CleanRL wrote",
        )
    except CheckpointError:  # an OSError too (FileNotFoundError): the refusal, as it is
        raise
    except OSError as error:
        raise CheckpointError(f"cannot load {what} {path}: {error.strerror or error}") from error
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
