"""Driving's picture of an episode: the car's lane over time, with its collisions and rescues."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.tasks.colors import COLORS

if TYPE_CHECKING:
    from matplotlib.axes import Axes

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
