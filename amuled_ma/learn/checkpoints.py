"""Read checkpoints without running code from them.

A PyTorch checkpoint is a pickle: loaded with ``weights_only`` off it may run any code
its author put in it. Every checkpoint and policy this package reads goes through
:func:`read_checkpoint`, which loads with ``torch.load(..., weights_only=True)`` (tensors,
numbers, strings and builtin containers only; PyTorch's restricted unpickler refuses any
other global before anything runs) and checks that the keys a caller needs are there.
rsl-rl's own ``OnPolicyRunner.load`` loads with ``weights_only`` off, so we never call it:
the trainer reads the state here and hands it to rsl-rl's public ``PPO.load``.

See ``docs/trust.md`` for what each input file may do.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from amuled_ma.errors import CheckpointError
from amuled_ma.torch_files import load_weights_only

#: Name of the newest checkpoint in a variant folder.
LAST = "model_last.pt"

#: Keys every checkpoint written by :class:`~amuled_ma.learn.trainer.Trainer` holds.
TRAINER_KEYS = ("actor_state_dict", "critic_state_dict", "optimizer_state_dict", "iter", "infos")


def read_checkpoint(path: str | Path, *, need: Iterable[str] = ("actor_state_dict",)) -> dict:
    """Load a checkpoint as plain data (``weights_only=True``) and check its keys.

    Args:
        path: The ``.pt`` file.
        need: Top-level keys the caller reads; a missing one is an error.

    Returns:
        The checkpoint's dict.

    Raises:
        CheckpointError: The file is missing, is not a weights-only checkpoint (it would
            need arbitrary code to load; nothing from it was run), is not a dict, or lacks
            a key in ``need``. The message names the file and what to do.

    """
    path = Path(path)
    try:
        state = load_weights_only(path, "checkpoint")
    except CheckpointError as error:
        if not path.is_file():
            raise
        raise CheckpointError(
            f"{error}; retrain it (--force), or convert a checkpoint you trust to plain "
            "tensors and numbers"
        ) from error.__cause__
    if not isinstance(state, dict):
        raise CheckpointError(
            f"cannot load checkpoint {path}: expected a dict of state dicts, found "
            f"{type(state).__name__}; retrain it with --force"
        )
    missing = [key for key in need if key not in state]
    if missing:
        raise CheckpointError(
            f"checkpoint {path} lacks {', '.join(repr(k) for k in missing)} (found keys: "
            f"{', '.join(sorted(map(str, state))) or 'none'}); it was not written by amuled, "
            "or is damaged: retrain it with --force"
        )
    return state


def checkpoint_infos(path: str | Path) -> dict[str, Any] | None:
    """Return a checkpoint's ``infos`` (our book-keeping), None when there is no file.

    Raises:
        CheckpointError: The file exists but cannot be read safely.

    """
    path = Path(path)
    if not path.is_file():
        return None
    infos = read_checkpoint(path, need=()).get("infos")
    return infos if isinstance(infos, dict) else {}
