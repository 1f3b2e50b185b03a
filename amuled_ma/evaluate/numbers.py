"""Numbers as the report, ``amuled explain`` and the figures print them.

Two rules: a count is printed as an integer (``2706``, not ``2706.0``; a mean over seeds
that is not whole keeps one decimal, ``2706.5``), and a value rounded to zero has no sign
(``0.0000``, not ``-0.0000``).
"""

from __future__ import annotations

import math

import numpy as np


def format_number(value: object, digits: int = 4) -> str:
    """A table cell: an integer as an integer, a float with ``digits`` decimals, no ``-0``.

    Args:
        value: An ``int``, a float (NumPy's included), or anything else (``str``).
        digits: Decimals of a float.

    Returns:
        ``"3"`` for ``3``, ``"0.1235"`` for ``0.12345``, ``"0.0000"`` for ``-1e-9``,
        ``"nan"`` / ``"inf"`` for non-finite floats.

    """
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        value = float(value)
        if not math.isfinite(value):
            return str(value)
        text = f"{value:.{digits}f}"
        if text.startswith("-") and float(text) == 0.0:
            return text[1:]
        return text
    return str(value)


def format_count(value: object, digits: int = 1) -> str:
    """A count (states, steps, answers): whole -> an integer; a mean over seeds keeps decimals.

    Args:
        value: An ``int`` or float, or None (``""``).
        digits: Decimals of a count that is not whole (a mean over seeds).

    Returns:
        ``"2706"`` for ``2706.0``, ``"2706.5"`` for ``2706.5``, ``""`` for None.

    """
    if value is None:
        return ""
    if isinstance(value, float | np.floating) and math.isfinite(value) and value.is_integer():
        return str(int(value))
    if isinstance(value, float | np.floating):
        return format_number(value, digits)
    return format_number(value)
