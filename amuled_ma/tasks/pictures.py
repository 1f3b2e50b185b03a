"""A task state as a short text picture for a person (the terminal agent's question).

Imports neither torch nor a task module.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from amuled_ma.errors import ScenarioError
from amuled_ma.tasks.names import canonical_name

#: FindMilk's grid side (cells); Driving's lanes.
_MILK_SIZE = 8
_DRIVING_LANES = 5


def _findmilk(obs: Sequence[float]) -> str:
    """The 8x8 grid, ``y`` up: ``R`` robot, ``M`` milk, ``C`` / ``z`` nearest crying / sleeping."""
    x, y, mx, my, cx, cy, sx, sy = (round(float(v)) for v in obs)
    marks = {(mx, my): "M"}
    known = []
    if (cx, cy) != (0, 0):  # (0, 0): none of that kind is left
        marks[(cx, cy)] = "C"
        known.append(f"C nearest crying baby ({cx}, {cy})")
    if (sx, sy) != (0, 0):
        marks[(sx, sy)] = "z"
        known.append(f"z nearest sleeping baby ({sx}, {sy})")
    marks[(x, y)] = "R"
    rows = [
        f"  y={row} " + " ".join(marks.get((col, row), ".") for col in range(_MILK_SIZE))
        for row in range(_MILK_SIZE - 1, -1, -1)
    ]
    rows.append("      " + " ".join(str(col) for col in range(_MILK_SIZE)) + "  = x")
    legend = ", ".join([f"R you ({x}, {y})", f"M milk ({mx}, {my})", *known])
    rows.append(f"  {legend}; only the nearest baby of each kind is known")
    return "\n".join(rows)


def _distance(value: int, what: str) -> str:
    return {-2: "", -1: f"no {what}"}.get(value, f"{what} {value} ahead")


def _driving(obs: Sequence[float]) -> str:
    """Your lane and its neighbours: the nearest car and grandma ahead in each."""
    values = [round(float(v)) for v in obs]
    lane = values[6:].index(1)
    lines = [f"  you drive on lane {lane} (lanes 0..{_DRIVING_LANES - 1})"]
    for name, (car, grandma) in (
        ("left lane   ", values[2:4]),
        ("your lane   ", values[0:2]),
        ("right lane  ", values[4:6]),
    ):
        if car == -2:
            lines.append(f"  {name}none (road edge)")
        else:
            lines.append(f"  {name}{_distance(car, 'car')}, {_distance(grandma, 'grandma')}")
    return "\n".join(lines)


#: Task -> (observation length, its picture): Driving's is six distances (current, left,
#: right lane: car, grandma), then the one-hot lane.
_PICTURES: dict[str, tuple[int, Callable[[Sequence[float]], str]]] = {
    "findmilk": (8, _findmilk),
    "driving": (6 + _DRIVING_LANES, _driving),
}


def state_picture(task: str, obs: Sequence[float]) -> str | None:
    """The state as lines of text; None without a picture or for an obs of another length."""
    try:
        key = canonical_name(task)
    except ScenarioError:
        return None
    length, draw = _PICTURES.get(key, (-1, _findmilk))
    if len(obs) != length:
        return None
    try:
        return draw(obs)
    except (ValueError, OverflowError):  # not finite, or a lane one-hot without a 1
        return None
