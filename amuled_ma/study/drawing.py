"""A state drawn as a small, self-contained, deterministic SVG in the viewer's `COLORS`."""

from __future__ import annotations

from collections.abc import Sequence
from html import escape
from typing import Any

from amuled_ma.tasks.colors import COLORS

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

    ink, grid = COLORS["ink"], COLORS["grid"]
    body = [f'<rect width="{size * CELL}" height="{size * CELL}" fill="#ffffff"/>']
    for i in range(size + 1):
        body.append(
            f'<line x1="{i * CELL}" y1="0" x2="{i * CELL}" y2="{size * CELL}" stroke="{grid}"/>'
        )
        body.append(
            f'<line x1="0" y1="{i * CELL}" x2="{size * CELL}" y2="{i * CELL}" stroke="{grid}"/>'
        )
    for kind, cells in (("sleeping", sleeping), ("crying", crying)):
        for cell in cells:  # as the viewer: the kind's colour, its letter, a dark edge
            x, y = xy(cell)
            shape = (
                f'<circle cx="{x}" cy="{y}" r="14"'
                if kind == "crying"
                else f'<rect x="{x - 13}" y="{y - 13}" width="26" height="26" rx="3"'
            )
            body.append(
                f'<g class="{kind}">{shape} fill="{COLORS[kind]}" stroke="{ink}" '
                f'stroke-width="1.5"/><text x="{x}" y="{y + 4}" text-anchor="middle" '
                f'fill="{ink}" font-size="11" font-weight="700">'
                f"{'C' if kind == 'crying' else 'z'}</text></g>"
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
    body.append(f'<polygon class="milk" points="{star}" fill="{COLORS["milk"]}" stroke="{ink}"/>')
    rx, ry = xy(robot)
    body.append(
        f'<rect class="robot" x="{rx - 11}" y="{ry - 11}" width="22" height="22" rx="4" '
        f'fill="{COLORS["agent"]}"/>'
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

    body = [f'<rect width="{width}" height="{height}" fill="{COLORS["road"]}"/>']
    for i in range(1, lanes):
        body.append(
            f'<line x1="{i * CELL}" y1="0" x2="{i * CELL}" y2="{height}" '
            f'stroke="{COLORS["lane_mark"]}" stroke-dasharray="8 8"/>'
        )
    for ln, d in cars:
        if 0 < int(d) <= distance:
            x, y = xy(ln, d)
            body.append(
                f'<rect class="car" x="{x - 11}" y="{y - 15}" width="22" height="30" rx="4" '
                f'fill="{COLORS["car"]}"/>'
            )
    for ln, d in grandmas:
        if 0 < int(d) <= distance:
            x, y = xy(ln, d)
            body.append(
                f'<circle class="grandma" cx="{x}" cy="{y}" r="10" fill="{COLORS["grandma"]}" '
                'stroke="#fff" stroke-width="2"/>'
            )
    x, y = xy(lane, 0)
    body.append(
        f'<rect class="agent" x="{x - 12}" y="{y - 16}" width="24" height="32" rx="4" '
        f'fill="{COLORS["agent"]}" stroke="#fff" stroke-width="2"/>'
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


def state_svg(
    task: str, layout: dict[str, Any] | None, frames: Sequence[Any], step: int, obs: Sequence[float]
) -> str:
    """The picture of state ``step`` of an episode (its frames and layout, see episode_trace)."""
    frame = frames[step]
    if task == "findmilk" and layout is not None:
        # entering a baby's cell removes it: the babies still in the room at ``step``
        visited = {tuple(int(v) for v in f) for f in frames[1 : step + 1]}
        crying = [list(p) for p in layout.get("crying", []) if tuple(p) not in visited]
        sleeping = [list(p) for p in layout.get("sleeping", []) if tuple(p) not in visited]
        milk = [round(obs[2]), round(obs[3])]
        return findmilk_svg(int(layout["size"]), frame, milk, crying, sleeping)
    if task == "driving" and layout is not None:
        lane, cars, grandmas = frame
        return driving_svg(int(layout["lanes"]), int(layout["distance"]), lane, cars, grandmas)
    return text_svg(str(frame))
