"""A job's settings as its plan computes them, for tests that name the variant as text."""

from __future__ import annotations

from typing import Any

from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.experiments.training_settings import training_config
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import Scenario


def settings(scenario: Scenario, text: str, **options: Any) -> dict[str, Any]:
    """``training_config`` of the variant ``text`` with its panel planned (``seed``, ...)."""
    variant = Variant.parse(text)
    panel = plan_panel(variant.feedback, scenario) if variant.feedback is not None else None
    return training_config(scenario, variant, panel=panel, **options)
