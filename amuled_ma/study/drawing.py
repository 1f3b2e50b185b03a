"""A state drawn as a small, self-contained SVG (what a participant sees of an item).

The pictures follow the report's and the viewer's conventions: FindMilk is the grid with
``y`` growing upwards, the robot, the milk (gold star), the crying babies (red discs) and the
sleeping babies (blue squares) still in the room; Driving is the five-lane road seen from
behind the car, with the cars (grey) and the grandmas (green) ahead at their distance. The
text is deterministic (fixed number formats, no ids from a counter), so a rebuilt study has
the same bytes.
"""

from __future__ import annotations

from collections.abc import Sequence
from html import escape
from typing import Any

CELL = 40


def _svg(width: int, height: int, body: list[str], title: str) -> str:
    head = (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" role="img" aria-label="{escape(title)}">'
    )
    return "\n".join([head, f"<title>{escape(title)}</title>", *body, "</svg>"]) + "\n"


def findmilk_svg(
    size: int,
    robot: Sequence[int],
    milk: Sequence[int],
    crying: Sequence[Sequence[int]],
    sleeping: Sequence[Sequence[int]],
) -> str:
    """The FindMilk grid with the robot, the milk and the babies still in the room."""

    def xy(cell: Sequence[int]) -> tuple[int, int]:
        return int(cell[0]) * CELL + CELL // 2, (size - 1 - int(cell[1])) * CELL + CELL // 2

    body = [f'<rect width="{size * CELL}" height="{size * CELL}" fill="#fbfbf8"/>']
    for i in range(size + 1):
        body.append(
            f'<line x1="{i * CELL}" y1="0" x2="{i * CELL}" y2="{size * CELL}" stroke="#ccc"/>'
        )
        body.append(
            f'<line x1="0" y1="{i * CELL}" x2="{size * CELL}" y2="{i * CELL}" stroke="#ccc"/>'
        )
    for cell in sleeping:
        x, y = xy(cell)
        body.append(
            f'<rect class="sleeping" x="{x - 13}" y="{y - 13}" width="26" height="26" '
            'fill="#8ecae6" stroke="#219ebc" stroke-width="2"/>'
        )
    for cell in crying:
        x, y = xy(cell)
        body.append(
            f'<circle class="crying" cx="{x}" cy="{y}" r="13" fill="#f28482" '
            'stroke="#c1121f" stroke-width="2"/>'
        )
    mx, my = xy(milk)
    star = " ".join(
        f"{mx + r * c:.1f},{my + r * s:.1f}"
        for r, c, s in (
            (15, 0.0, -1.0), (6, 0.588, -0.809), (15, 0.951, -0.309), (6, 0.951, 0.309),
            (15, 0.588, 0.809), (6, 0.0, 1.0), (15, -0.588, 0.809), (6, -0.951, 0.309),
            (15, -0.951, -0.309), (6, -0.588, -0.809),
        )
    )  # fmt: skip
    body.append(f'<polygon class="milk" points="{star}" fill="gold" stroke="#000"/>')
    rx, ry = xy(robot)
    body.append(
        f'<rect class="robot" x="{rx - 9}" y="{ry - 9}" width="18" height="18" rx="4" '
        'fill="#333" stroke="#000"/>'
    )
    title = (
        f"FindMilk: robot at ({int(robot[0])}, {int(robot[1])}), milk at ({int(milk[0])}, "
        f"{int(milk[1])}), {len(crying)} crying and {len(sleeping)} sleeping babies"
    )
    return _svg(size * CELL, size * CELL, body, title)


def driving_svg(
    lanes: int, distance: int, lane: int, cars: Sequence[Sequence[int]], grandmas: Sequence[Any]
) -> str:
    """The road: ``lanes`` lanes, ``distance`` rows ahead, the car on the bottom row."""
    width, height = lanes * CELL, (distance + 1) * CELL

    def xy(ln: int, d: int) -> tuple[int, int]:
        return int(ln) * CELL + CELL // 2, (distance - int(d)) * CELL + CELL // 2

    body = [f'<rect width="{width}" height="{height}" fill="#555"/>']
    for i in range(1, lanes):
        body.append(
            f'<line x1="{i * CELL}" y1="0" x2="{i * CELL}" y2="{height}" stroke="#eee" '
            'stroke-dasharray="8 8"/>'
        )
    for ln, d in cars:
        if 0 < int(d) <= distance:
            x, y = xy(ln, d)
            body.append(
                f'<rect class="car" x="{x - 11}" y="{y - 15}" width="22" height="30" rx="4" '
                'fill="#adb5bd" stroke="#000"/>'
            )
    for ln, d in grandmas:
        if 0 < int(d) <= distance:
            x, y = xy(ln, d)
            body.append(
                f'<circle class="grandma" cx="{x}" cy="{y}" r="11" fill="#2a9d8f" stroke="#fff" '
                'stroke-width="2"/>'
            )
    x, y = xy(lane, 0)
    body.append(
        f'<rect class="agent" x="{x - 12}" y="{y - 16}" width="24" height="32" rx="5" '
        'fill="#e63946" stroke="#fff" stroke-width="2"/>'
    )
    title = (
        f"Driving: your car in lane {int(lane)} of {lanes}, {len(cars)} cars and "
        f"{len(grandmas)} grandmas ahead"
    )
    return _svg(width, height, body, title)


def text_svg(text: str) -> str:
    """Any other task: its text picture, one line per row."""
    lines = str(text).splitlines() or [""]
    body = [
        f'<text x="8" y="{20 + 16 * i}" font-family="monospace" font-size="14">'
        f"{escape(line)}</text>"
        for i, line in enumerate(lines)
    ]
    width = 16 + 9 * max(len(line) for line in lines)
    return _svg(width, 24 + 16 * len(lines), body, "the state")


def remaining_babies(
    layout: dict[str, Any], frames: Sequence[Any], step: int
) -> tuple[list[list[int]], list[list[int]]]:
    """FindMilk babies still in the room at ``step``: entering a baby's cell removes it."""
    visited = {tuple(int(v) for v in f) for f in frames[1 : step + 1]}
    crying = [list(p) for p in layout.get("crying", []) if tuple(p) not in visited]
    sleeping = [list(p) for p in layout.get("sleeping", []) if tuple(p) not in visited]
    return crying, sleeping


def state_svg(
    task: str, layout: dict[str, Any] | None, frames: Sequence[Any], step: int, obs: Sequence[float]
) -> str:
    """The picture of state ``step`` of an episode (its frames and layout, see episode_trace)."""
    frame = frames[step]
    if task == "findmilk" and layout is not None:
        crying, sleeping = remaining_babies(layout, frames, step)
        milk = [round(obs[2]), round(obs[3])]
        return findmilk_svg(int(layout["size"]), frame, milk, crying, sleeping)
    if task == "driving" and layout is not None:
        lane, cars, grandmas = frame
        return driving_svg(int(layout["lanes"]), int(layout["distance"]), lane, cars, grandmas)
    return text_svg(str(frame))
