"""LLM feedback on a budget: a reward model distilled from the panel's answers (docs/distill.md)."""

from amuled_ma.distill.budget import BudgetExceeded, BudgetLedger, budget_cap
from amuled_ma.distill.model import EnsembleModel, FitSettings
from amuled_ma.distill.selection import choose_random, choose_uncertain, disagreement
from amuled_ma.distill.source import DistilledSource

__all__ = [
    "BudgetExceeded",
    "BudgetLedger",
    "DistilledSource",
    "EnsembleModel",
    "FitSettings",
    "budget_cap",
    "choose_random",
    "choose_uncertain",
    "disagreement",
]
