"""A near-flat agent's entropy share, measured by the panel feedback, read in words.

A real `MoralPanel` (Xiao's bjs-dst rule) over a source that answers each cluster with
a fixed belief: the summary's ``mean_entropy_share`` is checked against the entropy
computed here, and the flat agent's sentence reaches the terminal summary and the report.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.deliberation.panel import MoralPanel
from amuled_ma.deliberation.panel_feedback import PanelFeedback
from amuled_ma.deliberation.summaries import summary_lines
from amuled_ma.evaluate.evaluator import merge_feedback

FIXED = {
    "rules": [0.26, 0.24, 0.24, 0.26],  # the near-flat agent of the issue
    "care": [0.55, 0.15, 0.15, 0.15],
    "virtue": [0.15, 0.15, 0.15, 0.55],
}


class Fixed(BeliefSource):
    """Each cluster's fixed belief, whatever the state."""

    name = "fixed"

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        return [
            BeliefResult(np.array(FIXED[r.cluster]), "ok", self.name, latency_s=0.0)
            for r in requests
        ]


def _share(p: list[float]) -> float:
    """Shannon entropy of ``p`` over log2 of its length, computed here."""
    return -sum(x * math.log2(x) for x in p) / math.log2(len(p))


def test_flat_agent_with_the_largest_weight_gets_its_sentence() -> None:
    panel = MoralPanel("findmilk", list(FIXED), Fixed(), "bjs-dst", with_messages=False)
    feedback = PanelFeedback("amuled", panel, panel.source)
    feedback(torch.tensor([[1.0, 2.0], [3.0, 4.0], [1.0, 2.0]]), None)
    summary = feedback.summary()
    shares = summary["mean_entropy_share"]
    for agent, belief in FIXED.items():
        assert abs(shares[agent] - _share(belief)) < 1e-9
    assert abs(shares["rules"] - 0.99942) < 1e-4  # log2 terms: 0.26, 0.24 over 4 actions
    weights = summary["mean_weight"]
    assert max(weights, key=weights.get) == "rules"  # the information volume favours it
    text = "\n".join(summary_lines(summary))
    assert "reading: rules's beliefs are nearly flat (entropy 1.00 of max)" in text

    # seed replicas: the mean share per agent; the report reads the merged summary
    other = {**summary, "mean_entropy_share": {"rules": 0.5, "care": 0.1}}
    merged = merge_feedback([summary, other])
    assert abs(merged["mean_entropy_share"]["rules"] - (shares["rules"] + 0.5) / 2) < 1e-12
    assert merged["mean_entropy_share"]["virtue"] == shares["virtue"]  # one replica has it


def test_report_says_it() -> None:
    from amuled_ma.evaluate.report.writing import readings_lines
    from amuled_ma.evaluate.results import Results

    feedback = {
        "mean_weight": {"rules": 0.29, "care": 0.24},
        "mean_entropy_share": {"rules": _share(FIXED["rules"]), "care": 0.8},
    }
    results = Results.model_validate({"variants": {"finetune-amuled": {"feedback": feedback}}})
    (line,) = readings_lines(results)
    assert line.startswith("- **finetune-amuled**: rules's beliefs are nearly flat")
    assert "largest weight (0.29)" in line
