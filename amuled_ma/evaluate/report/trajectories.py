"""Trajectory figures: one recorded greedy episode per variant, drawn by its task."""

from __future__ import annotations

from typing import TYPE_CHECKING

from amuled_ma.evaluate.report.plotting import (
    grid_axes,
    legend_below,
    pyplot,
    variant_colors,
)
from amuled_ma.evaluate.results import Results
from amuled_ma.tasks.drawing import draw_driving, draw_findmilk, driving_legend, findmilk_legend

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def episode_figure(
    results: Results, mode: str = "greedy", colors: dict[str, str] | None = None
) -> Figure | None:
    """One recorded episode per variant, drawn by its task; None without ``mode`` or a drawing.

    FindMilk: a grid each, sub-goals marked; Driving: the lane over time, with events.
    """
    variants = {
        name: entry.trajectory.model_dump()
        for name, entry in results.in_mode(mode).items()
        if entry.trajectory is not None
    }
    if not variants or results.task not in ("findmilk", "driving"):
        return None
    colors = colors or variant_colors(variants)
    plt = pyplot()
    n = len(variants)
    if results.task == "findmilk":
        cols = 2 if n <= 4 else 3 if n <= 9 else 4
        fig, axes = grid_axes(plt, n, cols, 3.9, 4.4)
        for ax, (name, traj) in zip(axes, variants.items(), strict=False):
            draw_findmilk(ax, name, traj, colors.get(name, "k"))
        handles, labels = findmilk_legend()
        fig.suptitle(f"FindMilk {mode} trajectory, one per variant (path in the variant's colour)",
                     fontsize=9)  # fmt: skip
        legend_below(fig, handles, labels, axes[n:])
        return fig
    fig, rows = plt.subplots(
        n, 1, figsize=(10, 1.3 * n + 0.9), squeeze=False, sharex=True, layout="constrained"
    )
    for ax, (name, traj) in zip(rows[:, 0], variants.items(), strict=True):
        draw_driving(ax, name, traj, colors.get(name, "k"))
    rows[-1, 0].set_xlabel("step", fontsize=8)
    handles, labels = driving_legend()
    fig.legend(handles, labels, loc="outside upper right", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(f"Driving {mode} episode per variant: lane (0-4) over time, with events",
                 fontsize=9, x=0.02, ha="left")  # fmt: skip
    return fig
