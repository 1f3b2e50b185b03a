"""FindMilk's picture of an episode: the grid, the path, the milk, each baby pacified or woken.

The report draws one panel per variant with :func:`draw_findmilk`; the panel reads the
evaluator's recorded episode (``{"obs", "actions", "events", "layout"}``) and
:func:`findmilk_subgoals` says what it reached.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

#: The grid's side (cells).
SIZE = 8


def findmilk_subgoals(trajectory: Mapping[str, Any]) -> dict[str, Any]:
    """What a FindMilk trajectory did: babies pacified and woken, milk reached.

    Entering a baby's cell removes it (a crying one is pacified, a sleeping one woken), so
    the babies of the layout on the path are the ones the episode reached.

    Args:
        trajectory: ``{"obs": [[x, y, milk_x, milk_y, ...], ...], "layout": {"crying":
            [[x, y], ...], "sleeping": [...]}}`` (the evaluator's recorded episode).

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


def draw_findmilk(ax: Any, name: str, trajectory: Mapping[str, Any], color: str = "k") -> None:
    """Draw one FindMilk episode on a matplotlib axes.

    The path in ``color`` (start ▲, end ✕), the milk (★), every crying baby (red; green
    with ``+`` once pacified) and sleeping baby (blue; orange with ``!`` once woken); the
    title says the steps, whether the milk was reached and the babies pacified and woken.

    Args:
        ax: The axes.
        name: The variant (the title's first line).
        trajectory: The recorded episode.
        color: The variant's colour.

    """
    traj = trajectory
    size = SIZE
    goals = findmilk_subgoals(traj)
    obs = np.asarray(traj["obs"], dtype=float)
    for x, y in goals["sleeping"]:
        woken = (x, y) in goals["woken"]
        ax.scatter(x, y, marker="s", s=300, zorder=2, linewidths=2,
                   color="#f4a261" if woken else "#8ecae6",
                   edgecolor="#d62828" if woken else "#219ebc")  # fmt: skip
        if woken:
            ax.text(x, y, "!", ha="center", va="center", fontsize=12, weight="bold",
                    color="#d62828", zorder=6)  # fmt: skip
    for x, y in goals["crying"]:
        pacified = (x, y) in goals["pacified"]
        ax.scatter(x, y, marker="o", s=300, zorder=2, linewidths=2,
                   color="#b7e4c7" if pacified else "#f28482",
                   edgecolor="#2d6a4f" if pacified else "#c1121f")  # fmt: skip
        if pacified:
            ax.text(x, y, "+", ha="center", va="center", fontsize=13, weight="bold",
                    color="#2d6a4f", zorder=6)  # fmt: skip
    mx, my = goals["milk"]
    ax.scatter(mx, my, marker="*", s=330, color="gold", edgecolor="k", zorder=3)
    jitter = np.linspace(-0.13, 0.13, len(obs))
    ax.plot(obs[:, 0] + jitter, obs[:, 1] + jitter, "-", color=color,
            lw=2.0, alpha=0.9, zorder=4, gid="path")  # fmt: skip
    sx, sy = goals["start"]
    ax.scatter(sx, sy, marker="^", s=90, color="green", edgecolor="k", zorder=5)
    ex, ey = goals["end"]
    ax.scatter(ex, ey, marker="X", s=90, color="k", zorder=5)
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
    """The legend's handles and labels of :func:`draw_findmilk`'s markers."""
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], marker="^", ls="", color="green", markeredgecolor="k", ms=8),
        Line2D([], [], marker="X", ls="", color="k", ms=8),
        Line2D([], [], marker="*", ls="", color="gold", markeredgecolor="k", ms=13),
        Line2D([], [], marker="o", ls="", color="#f28482", markeredgecolor="#c1121f", ms=10),
        Line2D([], [], marker="o", ls="", color="#b7e4c7", markeredgecolor="#2d6a4f", ms=10),
        Line2D([], [], marker="s", ls="", color="#8ecae6", markeredgecolor="#219ebc", ms=10),
        Line2D([], [], marker="s", ls="", color="#f4a261", markeredgecolor="#d62828", ms=10),
    ]
    labels = ["start", "end", "milk", "crying baby", "crying baby pacified (+)",
              "sleeping baby", "sleeping baby woken (!)"]  # fmt: skip
    return handles, labels
