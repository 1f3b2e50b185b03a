"""Learning curves: one row per iteration and job, as a population writes them."""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

_T = TypeVar("_T")


def quiet(fn: Callable[[], _T]) -> _T:
    """Call ``fn`` with its prints to stdout dropped (rsl-rl's runner prints when built)."""
    with contextlib.redirect_stdout(io.StringIO()):
        return fn()


def curve_row(
    it: int,
    batch: int,
    wall_s: float,
    lr: float,
    episodes: list[dict],
    losses: dict,
    extra: dict,
) -> dict[str, Any]:
    """One ``curve.json`` row for iteration ``it`` (1-based): its episodes, losses, ``extra``."""
    row: dict[str, Any] = {
        "iteration": it,
        "env_steps": it * batch,
        "wall_s": round(wall_s, 4),
        "charts/lr": lr,
    }
    for key, value in losses.items():
        row[f"losses/{key}"] = float(value) if value is not None and math.isfinite(value) else None
    keys = sorted({k for e in episodes for k in e if k != "env_id"})
    row["charts/episodes"] = len(episodes)
    for key in keys:
        values = [e[key] for e in episodes if key in e]
        row[f"episode/{key}"] = float(np.mean(values)) if values else None
    for key, value in extra.items():
        row[f"feedback/{key}"] = value
    return row
