"""Each task's picture of a recorded episode, in the colours of `COLORS`.

FindMilk: the grid, the path, the milk, each baby pacified or woken. Driving: the car's lane
over time, with its collisions and rescues.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.tasks.colors import COLORS

if TYPE_CHECKING:
    from matplotlib.axes import Axes

#: The grid's side (cells).
SIZE = 8


def findmilk_subgoals(trajectory: Mapping[str, Any]) -> dict[str, Any]:
    """What a recorded FindMilk episode did: babies pacified and woken, milk reached.

    Entering a baby's cell removes it, so the layout's babies on the path are those reached.

    Returns:
        ``{"start", "milk", "end": (x, y), "visited": set of cells, "crying",
        "sleeping", "pacified", "woken": lists of (x, y), "reached_milk": bool}``.
    """
    obs = np.asarray(trajectory["obs"], dtype=float)
    cells = [(int(np.rint(x)), int(np.rint(y))) for x, y in obs[:, :2]]
    visited = set(cells[1:])
    layout = trajectory.get("layout") or {}
    crying = [tuple(int(v) for v in p) for p in layout.get("crying", [])]
    sleeping = [tuple(int(v) for v in p) for p in layout.get("sleeping", [])]
    milk = (int(np.rint(obs[0, 2])), int(np.rint(obs[0, 3])))
    return {
        "start": cells[0],
        "milk": milk,
        "end": cells[-1],
        "visited": visited,
        "crying": crying,
        "sleeping": sleeping,
        "pacified": [p for p in crying if p in visited],
        "woken": [p for p in sleeping if p in visited],
        "reached_milk": milk in visited,
    }


def _baby(ax: Axes, x: int, y: int, kind: str, reached: bool) -> None:
    """One baby: its kind's colour until reached, then its outcome's with a white glyph."""
    outcome = {"crying": ("pacified", "good", "\u2713"), "sleeping": ("woken", "bad", "!")}
    name, good_or_bad, glyph = outcome[kind]
    marker = "o" if kind == "crying" else "s"
    fill = COLORS[good_or_bad] if reached else COLORS[kind]
    ax.scatter(x, y, marker=marker, s=330, zorder=2, linewidths=1.6, color=fill,
               edgecolor=COLORS["ink"], gid=f"baby-{name if reached else kind}")  # fmt: skip
    ax.text(x, y, glyph if reached else ("C" if kind == "crying" else "z"), ha="center",
            va="center_baseline", fontsize=11 if reached else 8, weight="bold",
            color="white" if reached else COLORS["ink"], zorder=6)  # fmt: skip


def draw_findmilk(ax: Axes, name: str, trajectory: Mapping[str, Any], color: str = "k") -> None:
    """Draw one recorded FindMilk episode on ``ax`` in the colours of `COLORS`.

    The path, the milk (★), crying babies (``C``, green ✓ once pacified) and sleeping babies
    (``z``, red ``!`` once woken); the title says the steps and what was reached.
    """
    traj = trajectory
    size = SIZE
    goals = findmilk_subgoals(traj)
    obs = np.asarray(traj["obs"], dtype=float)
    for x, y in goals["sleeping"]:
        _baby(ax, x, y, "sleeping", (x, y) in goals["woken"])
    for x, y in goals["crying"]:
        _baby(ax, x, y, "crying", (x, y) in goals["pacified"])
    mx, my = goals["milk"]
    ax.scatter(mx, my, marker="*", s=380, color=COLORS["milk"], edgecolor=COLORS["ink"], zorder=3)
    jitter = np.linspace(-0.13, 0.13, len(obs))
    ax.plot(obs[:, 0] + jitter, obs[:, 1] + jitter, "-", color=color,
            lw=2.0, alpha=0.9, zorder=4, gid="path")  # fmt: skip
    sx, sy = goals["start"]
    ax.scatter(sx, sy, marker="^", s=90, color=COLORS["start"], edgecolor=COLORS["ink"],
               linewidths=1.4, zorder=5)  # fmt: skip
    ex, ey = goals["end"]
    ax.scatter(ex, ey, marker="X", s=90, color=COLORS["agent"], edgecolor="white", zorder=5)
    ax.set_xlim(-0.5, size - 0.5)
    ax.set_ylim(-0.5, size - 0.5)
    ax.set_xticks(range(size))
    ax.set_yticks(range(size))
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.set_aspect("equal")
    milk = "milk reached" if goals["reached_milk"] else "milk NOT reached"
    ax.set_title(
        f"{name}\n{len(traj['actions'])} steps, {milk}\n"
        f"pacified {len(goals['pacified'])}/{len(goals['crying'])}, "
        f"woken {len(goals['woken'])}/{len(goals['sleeping'])}",
        fontsize=8, color=color,
    )  # fmt: skip


def findmilk_legend() -> tuple[list[Any], list[str]]:
    """The legend's handles and labels of `draw_findmilk`'s markers."""
    from matplotlib.lines import Line2D

    ink = COLORS["ink"]
    handles = [
        Line2D([], [], marker="^", ls="", color=COLORS["start"], markeredgecolor=ink, ms=8),
        Line2D([], [], marker="X", ls="", color=COLORS["agent"], ms=8),
        Line2D([], [], marker="*", ls="", color=COLORS["milk"], markeredgecolor=ink, ms=13),
        Line2D([], [], marker="o", ls="", color=COLORS["crying"], markeredgecolor=ink, ms=10),
        Line2D([], [], marker="o", ls="", color=COLORS["good"], markeredgecolor=ink, ms=10),
        Line2D([], [], marker="s", ls="", color=COLORS["sleeping"], markeredgecolor=ink, ms=10),
        Line2D([], [], marker="s", ls="", color=COLORS["bad"], markeredgecolor=ink, ms=10),
    ]
    labels = ["start", "end", "milk", "crying baby (C)", "crying baby pacified (\u2713)",
              "sleeping baby (z)", "sleeping baby woken (!)"]  # fmt: skip
    return handles, labels


#: Events marked on the strip: ``{key: (marker, colour, size)}`` (the viewer's colours:
#: a collision is "bad", a rescue "good", `COLORS`).
DRIVING_EVENTS = {
    "collisions": ("X", COLORS["bad"], 90),
    "rescues": ("*", COLORS["good"], 140),
}


def draw_driving(ax: Axes, name: str, trajectory: Mapping[str, Any], color: str = "k") -> None:
    """Draw one recorded Driving episode on ``ax``: the lane (0-4) per step and its events."""
    traj = trajectory
    obs = np.asarray(traj["obs"], dtype=float)
    lane = obs[:, -5:].argmax(axis=1) if obs.shape[1] >= 5 else np.zeros(len(obs), int)
    steps = np.arange(len(lane))
    ax.step(steps, lane, where="post", color=color, lw=1.6, gid="path")
    events = traj.get("events") or {}
    counts = []
    for key, (marker, colour, size) in DRIVING_EVENTS.items():
        values = events.get(key, [])
        hits = [i + 1 for i, v in enumerate(values) if v]
        counts.append(f"{key} {int(sum(v for v in values if v))}")
        if hits:
            ax.scatter(hits, lane[hits], marker=marker, color=colour, s=size, zorder=3,
                       edgecolor=COLORS["ink"], linewidths=0.6, gid=f"event-{key}")  # fmt: skip
    changes = int(np.count_nonzero(np.diff(lane)))
    ax.set_title(f"{name}: {len(traj['actions'])} steps, {', '.join(counts)}, "
                 f"lane changes {changes}", fontsize=8, loc="left", color=color)  # fmt: skip
    ax.set_ylim(-0.5, 4.5)
    ax.set_yticks(range(5))
    ax.tick_params(labelsize=7)
    ax.set_ylabel("lane", fontsize=7)
    ax.grid(alpha=0.3)


def driving_legend() -> tuple[list[Any], list[str]]:
    """The legend's handles and labels of `draw_driving`'s event markers."""
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], marker=m, ls="", color=c, markeredgecolor=COLORS["ink"], ms=9)
        for m, c, _ in DRIVING_EVENTS.values()
    ]
    return handles, ["collision", "grandma rescued"]
