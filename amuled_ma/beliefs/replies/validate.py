"""The one rule of a valid belief, used at every door (files, store, imports, answers).

A belief: one finite non-negative real per action, summing to 1 within `SUM_TOLERANCE` (1e-6,
above float32 rounding); the check is idempotent, so a belief keeps its bits through every door.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TypeGuard

import numpy as np

from amuled_ma.errors import AmuledError

if TYPE_CHECKING:
    from amuled_ma.beliefs.types import BeliefResult

#: Largest accepted ``abs(sum(belief) - 1)``.
SUM_TOLERANCE = 1e-6
#: Largest ``abs(sum(belief) - 1)`` taken as float64 rounding: such a belief is kept as is;
#: one further off (but within `SUM_TOLERANCE`) is divided by its sum.
ROUNDING = 1e-12
#: Statuses whose result must hold a valid belief (the answers served back by the store).
ANSWER_STATUSES = frozenset({"ok", "repaired"})
#: What every error message says a belief must be.
RULE = (
    "a belief is a list of one finite, non-negative number per action, summing to 1 "
    f"(within {SUM_TOLERANCE:g})"
)

_MAX_SHOWN_CHARS = 120


class InvalidBeliefError(AmuledError, ValueError):
    """A belief vector is not a probability distribution over the task's actions."""


def show_values(values: object, limit: int = _MAX_SHOWN_CHARS) -> str:
    """``values`` as short plain text (``nan`` / ``inf``, never ``NaN``), cut at ``limit``."""
    try:
        if isinstance(values, np.ndarray):
            values = values.tolist()
        text = repr(values)
    except Exception:  # nested deeper than the stack allows, or an exotic repr that failed
        text = f"<{type(values).__name__} that repr cannot show>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _as_vector(values: object) -> tuple[np.ndarray | None, str | None]:
    """Return ``(float64 vector, None)`` or ``(None, why it is not a flat list of numbers)``."""
    if isinstance(values, np.ndarray):
        if values.dtype.kind not in "iuf":
            return None, f"is an array of {values.dtype}, not of real numbers"
        if values.ndim != 1:
            return None, f"has shape {values.shape}, not a flat list"
        return values.astype(np.float64, copy=False), None
    if isinstance(values, str | bytes) or not isinstance(values, Sequence):
        return None, f"is a {type(values).__name__}, not a list of numbers"
    for index, value in enumerate(values):
        if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
            what = "a list" if isinstance(value, list | tuple) else type(value).__name__
            return None, f"has {what} ({show_values(value, 40)}) at index {index}, not a number"
    try:
        return np.asarray(values, dtype=np.float64), None
    except OverflowError:  # an int beyond float64 (10**400)
        return None, "holds a number too large for a float (overflow)"


def _is_float_vector(values: object) -> TypeGuard[np.ndarray]:
    return isinstance(values, np.ndarray) and values.dtype == np.float64 and values.ndim == 1


def _sums_to_one(items: list[Any], n_actions: int) -> bool:
    """Fast check of a plain list: ``n_actions`` floats/ints in [0, 2] summing to 1 +- tol."""
    if len(items) != n_actions:
        return False
    total = 0.0
    for x in items:
        if (type(x) is not float and type(x) is not int) or not 0.0 <= x <= 2.0:
            return False
        total += x
    return abs(total - 1.0) <= SUM_TOLERANCE


def check_belief(
    values: object, n_actions: int, *, scores: bool = False
) -> tuple[np.ndarray | None, str | None]:
    """Check one belief of ``n_actions`` values (list, tuple or 1-D array); never raises.

    ``scores``: any positive finite sum (rules' answers), divided by it. Returns ``(belief,
    None)``, float64 divided by its sum unless 1 within `ROUNDING`, or ``(None, reason)``.
    """
    if not scores:  # the common case, a valid belief: plain Python, no numpy reductions
        items = values.tolist() if _is_float_vector(values) else values
        if type(items) is list and _sums_to_one(items, n_actions):
            vector = values if isinstance(values, np.ndarray) else np.array(items)
            total = float(sum(items))
            return (vector, None) if abs(total - 1.0) <= ROUNDING else (vector / total, None)
    as_vector, why = _as_vector(values)
    if as_vector is None:
        return None, why
    vector = as_vector
    if vector.shape != (n_actions,):
        return None, f"has {vector.size} value(s), expected {n_actions} (one per action)"
    finite = np.isfinite(vector)
    if not finite.all():
        index = int(np.argmin(finite))
        return None, f"holds {float(vector[index])!r} at index {index} (not a finite number)"
    if (vector < 0).any():
        index = int(np.argmax(vector < 0))
        return None, f"holds a negative value {float(vector[index])!r} at index {index}"
    with np.errstate(over="ignore"):
        total = float(vector.sum())
    if not math.isfinite(total):
        return None, f"sums to {total!r} (the values overflow)"
    if total <= 0.0:
        return None, "sums to 0 (every value is zero)"
    if not scores and abs(total - 1.0) > SUM_TOLERANCE:
        return None, f"sums to {total!r}, not 1 (tolerance {SUM_TOLERANCE:g})"
    if abs(total - 1.0) <= ROUNDING:
        return vector, None
    return vector / total, None


def validate_belief(
    values: object, n_actions: int, *, where: str, fix: str | None = None, scores: bool = False
) -> np.ndarray:
    """Return ``values`` as a valid float64 belief of ``n_actions`` (divided by its sum), or raise.

    `InvalidBeliefError` naming ``where`` (``"rec.json: states[3] 'care'"``), the reason, the
    values, the rule and ``fix``; ``scores`` as in `check_belief`.
    """
    belief, reason = check_belief(values, n_actions, scores=scores)
    if belief is None:
        raise InvalidBeliefError(
            f"{where}: invalid belief {show_values(values)}: it {reason}; {RULE}; "
            f"{fix or 'correct or remove it'}"
        )
    return belief


def check_beliefs(matrix: np.ndarray) -> tuple[np.ndarray, list[str | None]]:
    """Check the rows of an ``(m, A)`` float array at once (the panel's batch path).

    `check_belief` vectorised: ``(beliefs, reasons)``, valid rows divided by their sum (as
    there), invalid ones as they were; ``reasons[i]`` None for a valid row.
    """
    out = np.array(matrix, dtype=np.float64, copy=True)
    with np.errstate(invalid="ignore", over="ignore"):
        total = out.sum(axis=1)
        off = np.abs(total - 1.0)
        good = (
            np.isfinite(out).all(axis=1)
            & (out >= 0).all(axis=1)
            & np.isfinite(total)
            & (off <= SUM_TOLERANCE)
        )
    scale = good & (off > ROUNDING)
    out[scale] /= total[scale, None]
    reasons: list[str | None] = [None] * len(out)
    for i in np.flatnonzero(~good):
        reasons[i] = check_belief(matrix[i], out.shape[1])[1] or "is not a valid belief"
    return out, reasons


def uniform_belief(n_actions: int) -> np.ndarray:
    """Return the uniform belief over ``n_actions`` actions (the fallback of a failure)."""
    return np.full(n_actions, 1.0 / n_actions)


def checked_result(result: BeliefResult, n_actions: int, *, status: str = "error") -> BeliefResult:
    """Make a source's answer safe to store and fuse (changed in place); the door of live answers.

    A valid belief becomes `check_belief`'s; an invalid one becomes uniform, with the reason in
    ``extra["error"]`` and the values in ``extra["invalid_belief"]``, and an answer's status
    (`ANSWER_STATUSES`) becomes ``status`` (``"error"``: the source broke its contract).
    """
    belief, reason = check_belief(result.belief, n_actions)
    if belief is not None:
        result.belief = belief
        return result
    message = f"{result.source} gave an invalid belief: it {reason}"
    extra = dict(result.extra or {})
    extra["invalid_belief"] = show_values(result.belief)
    if result.status in ANSWER_STATUSES:
        extra["invalid_status"] = result.status
        result.status = status
        extra["error"] = message if "error" not in extra else f"{message}; {extra['error']}"
    else:
        extra.setdefault("error", message)
    result.belief = uniform_belief(n_actions)
    result.extra = extra
    return result
