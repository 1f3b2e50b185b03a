"""Numbers as the report, ``amuled explain`` and the figures print them."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np


def markdown_table(head: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A Markdown table: ``head``, its rule, a line per row, a newline; ``""`` without rows."""
    first, *rest = ["| " + " | ".join(cells) + " |" for cells in (head, *rows)]
    return "\n".join([first, "|" + "---|" * len(head), *rest]) + "\n" if rest else ""


def format_number(value: object, digits: int = 4) -> str:
    """A table cell: an int as an int, a float with ``digits`` decimals and no ``-0``."""
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
    """A count: whole -> ``2706``; a mean over seeds keeps ``digits`` decimals; None -> ``""``."""
    if value is None:
        return ""
    if isinstance(value, float | np.floating) and math.isfinite(value) and value.is_integer():
        return str(int(value))
    if isinstance(value, float | np.floating):
        return format_number(value, digits)
    return format_number(value)
