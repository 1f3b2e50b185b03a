"""A user cluster's TOML file for the cluster tests: its text, or the file written."""

from __future__ import annotations

from pathlib import Path

CLUSTER = """\
name = "{name}"
kind = "cluster"
order = {order}
title = "{title}"
credence_label = "{label}"
focus = "Focus on protecting the vulnerable"
key_principle = "Never leave anyone behind"

[[theories]]
name = "Stewardship"
key_concepts = ["Protection", "Duty of care"]
decision_factors = ["Vulnerability", "Risk"]
"""


def cluster_text(
    name: str, *, title: str = "Guardian Ethics", label: str | None = None, order: int = 10
) -> str:
    """A valid cluster file's text; the credence label is the title unless given."""
    return CLUSTER.format(name=name, title=title, label=label or title, order=order)


def write_cluster(
    directory: Path,
    name: str,
    *,
    title: str = "Guardian Ethics",
    label: str | None = None,
    order: int = 10,
) -> Path:
    """``directory/name.toml`` holding :func:`cluster_text`; returns its path."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.toml"
    path.write_text(cluster_text(name, title=title, label=label, order=order))
    return path
