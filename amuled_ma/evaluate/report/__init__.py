"""The run report: ``report.md`` with PNG figures (matplotlib, headless)."""

from __future__ import annotations

from amuled_ma.evaluate.report.plotting import format_stat
from amuled_ma.evaluate.report.writing import evaluation_outputs, link_viewer, write_report

__all__ = ["evaluation_outputs", "format_stat", "link_viewer", "write_report"]
