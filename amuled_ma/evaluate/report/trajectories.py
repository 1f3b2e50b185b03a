"""Trajectory figures: one recorded greedy episode per variant, drawn by its task."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

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


def _trajectories(results: Results, mode: str) -> dict[str, dict[str, Any]]:
    """``{variant: recorded episode}`` in ``mode``, as plain data."""
    return {
        name: entry.trajectory.model_dump()
        for name, entry in results.in_mode(mode).items()
        if entry.trajectory is not None
    }


def findmilk_figure(
    results: Results, mode: str = "greedy", colors: dict[str, str] | None = None
) -> Figure | None:
    """One FindMilk trajectory per variant, a grid each, sub-goals marked; None without ``mode``."""
    variants = _trajectories(results, mode)
    if not variants:
        return None
    colors = colors or variant_colors(variants)
    plt = pyplot()
    cols = 2 if len(variants) <= 4 else 3 if len(variants) <= 9 else 4
    fig, axes = grid_axes(plt, len(variants), cols, 3.9, 4.4)
    for ax, (name, traj) in zip(axes, variants.items(), strict=False):
        draw_findmilk(ax, name, traj, colors.get(name, "k"))
    spare = axes[len(variants) :]
    handles, labels = findmilk_legend()
    fig.suptitle(f"FindMilk {mode} trajectory, one per variant (path in the variant's colour)",
                 fontsize=9)  # fmt: skip
    legend_below(fig, handles, labels, spare)
    return fig


def driving_figure(
    results: Results, mode: str = "greedy", colors: dict[str, str] | None = None
) -> Figure | None:
    """One Driving episode per variant: its lane over time, events; None without ``mode``."""
    variants = _trajectories(results, mode)
    if not variants:
        return None
    colors = colors or variant_colors(variants)
    plt = pyplot()
    n = len(variants)
    fig, axes = plt.subplots(
        n, 1, figsize=(10, 1.3 * n + 0.9), squeeze=False, sharex=True, layout="constrained"
    )
    for ax, (name, traj) in zip(axes[:, 0], variants.items(), strict=True):
        draw_driving(ax, name, traj, colors.get(name, "k"))
    axes[-1, 0].set_xlabel("step", fontsize=8)
    handles, labels = driving_legend()
    fig.legend(handles, labels, loc="outside upper right", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(f"Driving {mode} episode per variant: lane (0-4) over time, with events",
                 fontsize=9, x=0.02, ha="left")  # fmt: skip
    return fig
