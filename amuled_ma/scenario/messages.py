"""Error rendering: pydantic's ``ValidationError`` as one scenario error line."""

from __future__ import annotations

import difflib
import re
import tomllib
import typing
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ValidationError

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.ranges import (
    RANGE_ERRORS,
    TOML_NAMES,
    Range,
    field_length,
    field_range,
    found,
)
from amuled_ma.scenario.ranges import kind as _kind

#: The section models by table name, in the order of a scenario file (filled by
#: `amuled_ma.scenario.sections`).
SECTIONS: dict[str, type[BaseModel]] = {}


#: The source named in errors of a scenario or section built in code (no file).
BUILT_IN_CODE = "<scenario built in code>"


def _type_name(tp: object) -> str:
    origin = typing.get_origin(tp)
    if origin is Annotated:
        return _type_name(typing.get_args(tp)[0])
    if origin is list:
        (inner,) = typing.get_args(tp)
        return f"list of {_type_name(inner)}"
    if origin is dict or (isinstance(tp, type) and issubclass(tp, BaseModel)):
        return "table"
    if origin is Literal:
        return f"string ({' or '.join(map(str, typing.get_args(tp)))})"
    if tp in (float, int, str, bool):
        return TOML_NAMES[tp]
    return getattr(tp, "__name__", str(tp))


def _number_type(annotation: object) -> object:
    """``int`` or ``float`` of a number key or a list of numbers (``list[Annotated[int, ...]]``)."""
    if typing.get_origin(annotation) is list:
        annotation = typing.get_args(annotation)[0]
    if typing.get_origin(annotation) is Annotated:
        annotation = typing.get_args(annotation)[0]
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if len(args) == 1 and type(None) in typing.get_args(annotation):  # ``int | None``
        return args[0]
    return annotation


def _float_for_int_hint(wants_int: bool, value: object) -> str:
    """Explain a float written where an integer is expected (TOML reads ``1e8`` as float)."""
    floats = [v for v in (value if isinstance(value, list) else [value]) if isinstance(v, float)]
    if not wants_int or not floats:
        return ""
    example = next((v for v in floats if v.is_integer()), None)
    if example is None:
        return "; an integer is needed here"
    return (
        f"; TOML reads {example!r} (written with a decimal point or an exponent such as 1e8) "
        f"as a float: write the integer as {int(example):_}"
    )


def did_you_mean(key: str, names: list[str]) -> str:
    """`` (did you mean X?)`` for the name closest to ``key``, or ``""``."""
    close = difflib.get_close_matches(key, names, n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def unknown_top_level(key: object, source: str) -> str:
    """The message of an unknown top-level key of a scenario file."""
    names = ["name", *SECTIONS]
    return (
        f"{source}: unknown section or key {key!r}{did_you_mean(str(key), names)}; expected "
        f"name or one of the tables {', '.join(f'[{s}]' for s in SECTIONS)}"
    )


def unknown_section(section: str, source: str) -> str:
    """The message of an unknown section."""
    return (
        f"{source}: unknown section [{section}]{did_you_mean(section, list(SECTIONS))}; "
        f"expected one of {', '.join(f'[{s}]' for s in SECTIONS)}"
    )


def _describe(error: Any, source: str, loc: tuple[Any, ...]) -> str:
    """One pydantic error (``loc`` from the scenario's top) as a scenario message."""
    kind, value = error["type"], error.get("input")
    found_it = f"found {found(value)}"
    if not loc:
        return f"{source}: {error['msg']}, {found_it}"
    head = loc[0]
    if head not in SECTIONS:  # a top-level key: name, or no key of a scenario file
        if kind == "extra_forbidden":
            return unknown_top_level(head, source)
        if kind == "string_type":
            return f"{source}: key {head} expects string, {found_it}"
        return f"{source}: key {head}: {error['msg']}, {found_it}"
    section, model = str(head), SECTIONS[str(head)]
    while len(loc) > 2 and (nested := _table_model(model, loc[1])) is not None:
        model = nested  # a nested table: [feedback.distill]
        section, loc = f"{section}.{loc[1]}", (loc[0], *loc[2:])
    if len(loc) == 1:
        if kind in ("model_type", "model_attributes_type", "dict_type"):
            return f"{source}: key {section} expects table, {found_it}"
        return f"{source}: key [{section}]: {error['msg']}, {found_it}"
    key, rest = str(loc[1]), loc[2:]
    names = list(model.model_fields)
    if kind == "extra_forbidden" and not rest:
        return (
            f"{source}: unknown key [{section}].{key}{did_you_mean(key, names)}; expected one "
            f"of: {', '.join(names)}"
        )
    where = f"[{section}].{key}"
    info = model.model_fields[key]  # pydantic reports only keys of the model
    index = rest[0] if rest and isinstance(rest[0], int) else None
    at = f" at index {index}" if index is not None else ""
    if kind in RANGE_ERRORS:
        rng = field_range(model, key) or Range()
        number_type = _number_type(info.annotation)
        if index is not None:
            where += f"[{index}]"
        return (
            f"{source}: key {where} expects {_kind(number_type, rng)} {rng.describe()} "
            f"({rng.why}), found {value!r}"
        )
    if kind in ("too_short", "too_long"):
        length = field_length(model, key) or Range()
        return (
            f"{source}: key {where} expects a list whose length is {length.describe()} "
            f"({length.why}), found {len(value)} entries ({value!r})"
        )
    if kind == "literal_error":
        tp = info.annotation if index is None else typing.get_args(info.annotation)[0]
        choices = ", ".join(map(str, typing.get_args(tp)))
        each = "each entry to be " if index is not None else ""
        return f"{source}: key {where} expects {each}one of {choices}, found {value!r}{at}"
    if kind.endswith("_type"):
        broken = toml_syntax_error(value) if kind in ("list_type", "dict_type") else None
        if broken is not None:
            opens = "list" if value.lstrip()[0] == "[" else "table"
            return (
                f"{source}: key {where} expects {_type_name(info.annotation)}, found "
                f"{value[:60]!r}, which opens a TOML {opens}"
                f" but is not TOML: {broken}; write strings in quotes and quote the whole "
                f"value on the command line: --set \"{where[1:].replace('].', '.')}=['a', 'b']\""
            )
        wants_int = kind == "int_type"
        return (
            f"{source}: key {where} expects {_type_name(info.annotation)}, {found_it}{at}"
            f"{_float_for_int_hint(wants_int, value)}"
        )
    return f"{source}: key {where}{at}: {error['msg']}, {found_it}"


def toml_syntax_error(value: object) -> str | None:
    """Why ``value``, opening a TOML list or table, is not TOML; None if it parses."""
    if not isinstance(value, str) or not value.lstrip().startswith(("[", "{")):
        return None
    text = value.strip()
    try:
        tomllib.loads(f"v = {text}")
    except tomllib.TOMLDecodeError as error:
        # the column in the value, not in "v = <value>"
        def column(match: re.Match[str]) -> str:
            return f"column {int(match.group(1)) - len('v = ')}"

        return re.sub(r"line 1, column (\d+)", column, str(error))

    except RecursionError:
        return "nested deeper than Python's TOML reader can follow"
    return None


def _table_model(model: type[BaseModel], key: object) -> type[BaseModel] | None:
    """The model of ``model``'s key when that key is a nested table, else None."""
    info = model.model_fields.get(str(key))
    tp = info.annotation if info is not None else None
    return tp if isinstance(tp, type) and issubclass(tp, BaseModel) else None


def scenario_error(error: ValidationError, source: str, loc: tuple[str, ...] = ()) -> ScenarioError:
    """Turn pydantic's ``ValidationError`` into one line: ``source``, key, expected and found.

    A validator's own `ScenarioError` is returned as it is; further problems are counted.
    ``loc`` is where the model sits (``("ppo",)`` or ``()``).
    """
    problems = error.errors(include_url=False)
    first = problems[0]
    cause = (first.get("ctx") or {}).get("error")
    if isinstance(cause, ScenarioError):
        return cause
    message = _describe(first, source, (*loc, *first["loc"]))
    more = len(problems) - 1
    if more:
        message += f" (and {more} more problem{'s' if more > 1 else ''})"
    return ScenarioError(message)
