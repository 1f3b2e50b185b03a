"""A job's settings as its plan computes them, for tests that name the variant as text."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.experiments.pipeline import PipelineRequest, train_alone
from amuled_ma.experiments.plans import ablation_variants
from amuled_ma.experiments.run_folder import JobResult, TrainJob
from amuled_ma.experiments.training_settings import training_config
from amuled_ma.learn.job_shape import JobShape, job_shape
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import Scenario


def job_of(scenario: Scenario, variant: Variant, **options: Any) -> TrainJob:
    """A job of ``variant`` on ``scenario`` (``seed``, ``iterations``, ...), folders here."""
    here = Path(".")
    return TrainJob("job", scenario, here, variant, here, **options)


def settings(scenario: Scenario, text: str, **options: Any) -> dict[str, Any]:
    """``training_config`` of the variant ``text`` with its panel planned (``seed``, ...)."""
    variant = Variant.parse(text)
    panel = plan_panel(variant.feedback, scenario) if variant.feedback is not None else None
    return training_config(job_of(scenario, variant, **options), panel)


def job_shape_of(scenario: Scenario, variant: Variant, iterations: int | None = None) -> JobShape:
    """``job_shape`` of ``variant`` from the scenario's sections."""
    return job_shape(
        scenario.ppo,
        scenario.base,
        scenario.finetune,
        variant,
        iterations,
        where=str(scenario.path or scenario.name),
    )


def ablation_jobs(what: str, scenario: Scenario) -> list[tuple[Variant, Scenario]]:
    """``ablation_variants`` of ``scenario``, each job's changes applied as plan_ablation does."""
    listed = ablation_variants(
        what, scenario.feedback, scenario.task.name, scenario.resolve, scenario.name
    )
    return [(variant, scenario.changed(changes)) for variant, changes in listed]


def train_variant(
    scenario: Scenario,
    run_dir: Path,
    variant: Variant,
    *,
    resume: bool = False,
    force: bool = False,
    **options: Any,
) -> JobResult:
    """``train_alone`` of ``variant`` into ``run_dir``, no bars (``iterations``, ``base_dir``)."""
    request = PipelineRequest(scenario, run_dir, resume=resume, force=force, progress=False)
    return train_alone(request, variant, **options)
