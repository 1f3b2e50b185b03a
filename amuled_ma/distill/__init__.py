"""LLM feedback on a budget: a reward model distilled from the panel's answers (docs/distill.md).

This package knows the belief types and the fusion; it knows nothing of the learner.
"""

from amuled_ma.distill.budget import BudgetExceeded, BudgetLedger, budget_cap, check_budget
from amuled_ma.distill.model import EnsembleModel, FitSettings
from amuled_ma.distill.selection import SELECTIONS, choose_random, choose_uncertain, disagreement
from amuled_ma.distill.source import (
    DISTILLED,
    DISTILLED_MISS,
    UNASKED,
    DistilledSource,
    DistillStats,
)

__all__ = [
    "DISTILLED",
    "DISTILLED_MISS",
    "SELECTIONS",
    "UNASKED",
    "BudgetExceeded",
    "BudgetLedger",
    "DistillStats",
    "DistilledSource",
    "EnsembleModel",
    "FitSettings",
    "budget_cap",
    "check_budget",
    "choose_random",
    "choose_uncertain",
    "disagreement",
]
