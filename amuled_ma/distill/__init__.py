"""LLM feedback on a budget: a reward model distilled from the panel's answers.

The moral panel is asked about a share of the distinct states a fine-tune visits (the
budget); a small ensemble of networks learns each panel member's belief from those
answers and answers every other state, and the selection asks where the ensemble is
unsure. See ``docs/distill.md``.

- :mod:`amuled_ma.distill.budget`: the budget rule and the ledger of visited and asked
  states (pure Python).
- :mod:`amuled_ma.distill.model`: the ensemble of MLPs (torch, own generator).
- :mod:`amuled_ma.distill.selection`: uncertainty (disagreement + novelty) and random.
- :mod:`amuled_ma.distill.state`: the state files that keep the budget across a resume.
- :mod:`amuled_ma.distill.source`: :class:`DistilledSource`, the panel's source behind
  the budget and the model.

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
