"""A scenario's feedback and panel source in one call, for tests: plan, then build."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from amuled_ma.beliefs.store.service import StoreService
from amuled_ma.clusters import Cluster
from amuled_ma.deliberation.build import build_feedback, panel_source, run_store
from amuled_ma.deliberation.feedback_base import Feedback
from amuled_ma.deliberation.plan import PanelPlan, plan_panel, plan_sources
from amuled_ma.scenario import MORAL_AGENT, Scenario


def make_feedback(
    variant: str,
    scenario: Scenario,
    run_dir: Path | None = None,
    *,
    state_dir: Path | None = None,
    resume: bool = False,
    seed: int | None = None,
    store: StoreService | None = None,
) -> Feedback:
    """`plan_panel` then `build_feedback`, over the run's store unless ``store`` is given."""
    plan = plan_panel(variant, scenario)
    if store is None:
        store = run_store(scenario.store_path(run_dir))
    return build_feedback(
        plan, store, state_dir=state_dir, resume=resume, seed=seed, cache_dir=run_dir
    )


class _Named:
    """A member known by name only."""

    def __init__(self, name: str) -> None:
        self.name = name


def make_source(
    scenario: Scenario,
    run_dir: Path | None = None,
    *,
    agents: Sequence[str | Cluster] | None = None,
):
    """The belief source of a panel of ``agents`` behind the run's store.

    ``agents`` defaults to ``[feedback].clusters`` and ``moral_agent``.
    """
    fb = scenario.feedback
    if agents is None:
        agents = [*fb.clusters, *([MORAL_AGENT] if MORAL_AGENT not in fb.clusters else [])]
    names = [a if isinstance(a, str) else a.name for a in agents]
    where = str(scenario.path or f"scenario {scenario.name!r}")
    routes, default, problems = plan_sources(fb, scenario.resolve, where, list(agents))
    plan = PanelPlan(
        variant="amuled",
        kind="amuled",
        task=scenario.task.name,
        where=str(scenario.path or scenario.name),
        seed=scenario.task.seed,
        clusters=tuple(_Named(n) for n in names),
        routes=routes,
        default=default,
        problems=tuple(problems),
    )
    return panel_source(plan, run_store(scenario.store_path(run_dir)))
