"""Reading a report's Markdown tables in tests."""

from __future__ import annotations


def rows_of(table: str) -> dict[str, list[str]]:
    """A Markdown table's rows by their first cell (its header and separator skipped)."""
    out = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        out[cells[0]] = cells[1:]
    return out
