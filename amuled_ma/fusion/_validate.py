"""Input checks shared by every fusion entry point (private)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

SUM_TOLERANCE = 1e-6
"""Largest accepted ``|sum(row) - 1|`` for a belief row or mass function."""

RESCALE_THRESHOLD = 1e-12
"""Rows are divided by their sums when some ``|sum(row) - 1|`` exceeds this (else used as is)."""


def _index_text(name: str, index: tuple[int, ...]) -> str:
    if not index:
        return name
    return f"{name}[{', '.join(str(int(i)) for i in index)}]"


def check_rows(values: object, name: str = "beliefs", *, min_ndim: int = 2) -> np.ndarray:
    """Return ``values`` (shape ``(..., n)``) as float64 rows rescaled to sum to 1 (read-only).

    Raises:
        ValueError: ``ndim < min_ndim``, an empty row, or a row with NaN/inf, a negative
            entry or a sum farther than `SUM_TOLERANCE` from 1 (names the row's index).
    """
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of numbers: {exc}") from None
    if array.ndim < min_ndim:
        raise ValueError(
            f"{name} must have at least {min_ndim} dimensions, got shape {array.shape}"
        )
    if array.shape[-1] == 0:
        raise ValueError(f"{name} must have at least one entry per row, got shape {array.shape}")
    if array.size == 0:
        return array
    # Fast path: three whole-array reductions. NaN/inf make a row sum non-finite, and a
    # NaN minimum or sum fails every comparison, so only bad input takes the slow path.
    sums = np.einsum("...i->...", array)
    lowest = array.min()
    if not (
        lowest >= 0 and sums.max() - 1.0 <= SUM_TOLERANCE and 1.0 - sums.min() <= SUM_TOLERANCE
    ):
        _raise_first_bad_row(array, sums, name)
    if max(sums.max() - 1.0, 1.0 - sums.min()) > RESCALE_THRESHOLD:
        array = array / sums[..., None]
    return array


def _raise_first_bad_row(array: np.ndarray, sums: np.ndarray, name: str) -> None:
    finite = np.asarray(np.isfinite(array).all(axis=-1))
    nonneg = np.asarray((array >= 0).all(axis=-1))
    close = np.abs(sums - 1.0) <= SUM_TOLERANCE
    good = finite & nonneg & close
    index = tuple(int(i) for i in np.argwhere(~good)[0])
    row = array[index]
    if not finite[index]:
        reason = "contains NaN or infinity"
    elif not nonneg[index]:
        reason = "has a negative entry"
    else:
        reason = f"sums to {float(sums[index])!r}, expected 1 within {SUM_TOLERANCE:g}"
    raise ValueError(
        f"{_index_text(name, index)} is not a probability vector: {reason} (got {row.tolist()})"
    )


def check_weights(
    weights: npt.ArrayLike, batch_shape: tuple[int, ...], name: str = "weights"
) -> np.ndarray:
    """Return per-cluster ``weights`` broadcast to ``batch_shape`` as float64.

    Raises ValueError: not broadcastable, NaN/inf, negative, or all zero for some leading index.
    """
    try:
        array = np.broadcast_to(np.asarray(weights, dtype=np.float64), batch_shape)
    except ValueError:
        shape = np.shape(weights)
        raise ValueError(
            f"{name} of shape {shape} do not broadcast to (..., n_clusters) = {batch_shape}"
        ) from None
    if array.size == 0:
        return array
    bad_entry = ~np.isfinite(array) | (array < 0)
    if bad_entry.any():
        index = tuple(int(i) for i in np.argwhere(bad_entry)[0])
        raise ValueError(
            f"{_index_text(name, index)} = {float(array[index])!r}: {name} must be "
            "finite and non-negative"
        )
    zero = array.sum(axis=-1) <= 0
    if zero.any():
        index = tuple(int(i) for i in np.argwhere(zero)[0])
        raise ValueError(
            f"{_index_text(name, index)} are all zero: at least one cluster needs weight"
        )
    return array
