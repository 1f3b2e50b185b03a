"""The run report: ``report.md`` with PNG figures (matplotlib, headless)."""

from __future__ import annotations

from amuled_ma.evaluate.report.bars import (
    ablation_figure,
    bars_figure,
    budget_figure,
    budget_points,
)
from amuled_ma.evaluate.report.curves import curve_band, curves_figure, load_curves
from amuled_ma.evaluate.report.describe import imported_table, panels_table, settings_table
from amuled_ma.evaluate.report.plotting import (
    compact_number,
    format_stat,
    robust_ylim,
    variant_colors,
)
from amuled_ma.evaluate.report.tables import (
    agents_table,
    base_differences,
    budget_ablation_table,
    budget_table,
    diagnostics_table,
    differences_table,
    metrics_table,
    same_as_base,
    servers_table,
)
from amuled_ma.evaluate.report.trajectories import (
    driving_figure,
    findmilk_figure,
)
from amuled_ma.evaluate.report.writing import (
    FIGURE_NAMES,
    VIEWER_PAGE,
    VIEWER_PREFIX,
    evaluation_outputs,
    link_viewer,
    viewer_line,
    write_report,
)
from amuled_ma.tasks.findmilk_drawing import findmilk_subgoals

__all__ = [
    "FIGURE_NAMES", "VIEWER_PAGE", "VIEWER_PREFIX", "ablation_figure", "agents_table",
    "bars_figure", "base_differences", "budget_ablation_table", "budget_figure", "budget_points",
    "budget_table", "compact_number", "curve_band", "curves_figure", "diagnostics_table",
    "differences_table", "driving_figure", "evaluation_outputs", "findmilk_figure",
    "findmilk_subgoals", "format_stat", "imported_table", "link_viewer", "load_curves",
    "metrics_table", "panels_table", "robust_ylim", "same_as_base", "servers_table",
    "settings_table", "variant_colors", "viewer_line", "write_report",
]  # fmt: skip
