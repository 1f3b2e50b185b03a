"""Declared number ranges of scenario keys, read back from the models' ``Field`` bounds."""

from __future__ import annotations

import typing
from dataclasses import dataclass
from typing import Annotated, Any

from pydantic import BaseModel

#: pydantic error types of a number outside its declared bounds (or NaN, infinite).
RANGE_ERRORS = frozenset(
    {"greater_than", "greater_than_equal", "less_than", "less_than_equal", "finite_number"}
)


@dataclass(frozen=True)
class Range:
    """The allowed values of a numeric scenario key (never NaN or inf)."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    why: str = ""

    def describe(self) -> str:
        """The range in words: ``in (0, 1]``, ``>= 1``, ``> 0``."""
        if self.low is not None and self.high is not None:
            left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
            return f"in {left}{_number(self.low)}, {_number(self.high)}{right}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {_number(self.low)}"
        if self.high is not None:
            return f"{'<' if self.high_open else '<='} {_number(self.high)}"
        return "(any finite value)"


def _number(value: float) -> str:
    if isinstance(value, int) and abs(value) >= 10_000:
        return f"{value:,}"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _bounds(metadata: list[Any], why: str | None) -> Range | None:
    """The ``ge``/``gt``/``le``/``lt`` constraints among a field's metadata as a Range."""
    low = high = None
    low_open = high_open = False
    for item in metadata:
        if getattr(item, "ge", None) is not None:
            low = item.ge
        elif getattr(item, "gt", None) is not None:
            low, low_open = item.gt, True
        if getattr(item, "le", None) is not None:
            high = item.le
        elif getattr(item, "lt", None) is not None:
            high, high_open = item.lt, True
    if low is None and high is None:
        return None
    return Range(low, high, low_open, high_open, why or "")


def field_range(model: type[BaseModel], key: str) -> Range | None:
    """The range of a numeric key (each entry's, for a list); None without bounds."""
    info = model.model_fields[key]
    if typing.get_origin(info.annotation) is list:  # list[Annotated[int, Field(...)]]
        (entry,) = typing.get_args(info.annotation)
        if typing.get_origin(entry) is Annotated:
            item = next((m for m in typing.get_args(entry)[1:] if hasattr(m, "metadata")), None)
            if item is not None:
                return _bounds(item.metadata, item.description)
    return _bounds(info.metadata, info.description)


def field_length(model: type[BaseModel], key: str) -> Range | None:
    """The allowed number of entries of a list key, or None when the length is free."""
    info = model.model_fields[key]
    low = next((m.min_length for m in info.metadata if hasattr(m, "min_length")), None)
    high = next((m.max_length for m in info.metadata if hasattr(m, "max_length")), None)
    if low is None and high is None:
        return None
    return Range(low, high, why=info.description or "")


def kind(number_type: object, rng: Range) -> str:
    """What a key of ``number_type`` (``int`` or ``float``) in ``rng`` is, in words."""
    if number_type is int:
        if rng.low is not None and rng.low >= 1:
            return "a positive integer"
        if rng.low == 0:
            return "a non-negative integer"
        return "an integer"
    return "a finite number"


#: The TOML name of each Python type a TOML value reads as.
TOML_NAMES = {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
              dict: "table"}  # fmt: skip


def found(value: object) -> str:
    """A value as messages show what was found: ``integer (3)``, ``table ({})``."""
    return f"{TOML_NAMES.get(type(value), type(value).__name__)} ({value!r})"
