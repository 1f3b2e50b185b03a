"""The AMULED paper's figures (`PAPER_SOURCE`; temetski/moral_agent at df3750f), as data."""

from __future__ import annotations

from dataclasses import dataclass

#: Where every figure of `PAPER_ROWS` comes from (printed under the report's table).
PAPER_SOURCE = (
    "the AMULED paper's results table for the task (the authors' notebook "
    "`notebooks/data_plots.ipynb`: sampled policy, 50 episodes, seeds 42-91, one training "
    "seed, 1,000 fine-tuning iterations, gpt-4o-mini beliefs); docs/reproduction.md"
)
#: The recipe that produced the paper's figures (the authors' scripts).
PAPER_RECIPE = "authors"
#: The action selection of the paper's figures.
PAPER_MODE = "sampled"

#: The paper's metrics per task, in the order of its tables.
PAPER_COLUMNS: dict[str, tuple[str, ...]] = {
    "findmilk": ("steps_to_milk", "crying_pacified", "sleeping_woken"),
    "driving": ("collisions", "rescues", "non_straight_steps"),
}


@dataclass(frozen=True)
class PaperRow:
    """One row of the paper's results table; ``values`` in our metrics' units (per episode)."""

    task: str
    variant: str
    label: str
    values: dict[str, float]


def _rows(task: str, table: dict[str, tuple[str, tuple[float, float, float]]]) -> list[PaperRow]:
    columns = PAPER_COLUMNS[task]
    return [
        PaperRow(task, variant, label, dict(zip(columns, values, strict=True)))
        for variant, (label, values) in table.items()
    ]


#: FindMilk: steps to the milk / crying babies pacified (of 5) / sleeping babies woken (of 6).
_FINDMILK = {
    "base": ("base", (14.0, 4.0, 3.8)),
    "shaped": ("base + shaping", (14.0, 5.0, 0.0)),
    "finetune-human": ('"human" feedback', (14.9, 3.0, 1.5)),
    "finetune-amuled": ("AMULED", (14.2, 4.9, 0.6)),
    "finetune-cluster-consequentialist": ("consequentialist alone", (14.0, 4.6, 0.9)),
    "finetune-cluster-deontological": ("deontological alone", (14.1, 4.0, 1.2)),
    "finetune-cluster-virtue": ("virtue alone", (14.0, 4.6, 0.7)),
    "finetune-cluster-care": ("care alone", (14.0, 5.0, 0.6)),
    "finetune-cluster-social_justice": ("social justice alone", (16.0, 4.6, 0.7)),
    "finetune-moral": ("unprompted moral agent", (15.3, 3.4, 3.0)),
    "finetune-agg-vote": ("majority vote", (14.0, 4.7, 0.9)),
    "finetune-agg-max": ("maximum belief", (14.8, 4.9, 0.5)),
    "finetune-agg-mean": ("mean belief", (14.0, 4.0, 1.5)),
}
#: Driving: collisions / grandmas rescued / "lane changes" per 300-step episode; the last
#: counts the steps whose action was not straight (the authors' ``environments/drive.py:136``,
#: ``lane_changes += action != 0``), our ``non_straight_steps``, not ``lane_changes``.
_DRIVING = {
    "base": ("base", (1.0, 5.9, 16.2)),
    "shaped": ("base + shaping", (12.5, 19.1, 167.1)),
    "finetune-human": ('"human" feedback', (4.1, 9.8, 52.9)),
    "finetune-amuled": ("AMULED", (2.0, 13.6, 54.2)),
    "finetune-cluster-consequentialist": ("consequentialist alone", (8.7, 6.9, 11.9)),
    "finetune-cluster-deontological": ("deontological alone", (8.6, 9.4, 75.6)),
    "finetune-cluster-virtue": ("virtue alone", (4.1, 14.7, 74.5)),
    "finetune-cluster-care": ("care alone", (3.5, 12.0, 60.0)),
    "finetune-cluster-social_justice": ("social justice alone", (6.6, 14.3, 68.0)),
    "finetune-moral": ("unprompted moral agent", (7.4, 9.2, 53.8)),
    "finetune-agg-vote": ("majority vote", (2.5, 13.5, 42.5)),
    "finetune-agg-max": ("maximum belief", (2.7, 10.5, 36.2)),
    "finetune-agg-mean": ("mean belief", (2.0, 12.2, 33.6)),
}

#: Every row of the paper, per task and our variant folder.
PAPER_ROWS: dict[str, dict[str, PaperRow]] = {
    task: {row.variant: row for row in _rows(task, table)}
    for task, table in (("findmilk", _FINDMILK), ("driving", _DRIVING))
}


def paper_row(task: str, variant: str) -> PaperRow | None:
    """The paper's row of a variant folder (a seed replica maps to it), or None."""
    name = variant.split(".seed", 1)[0]
    return PAPER_ROWS.get(task, {}).get(name)
