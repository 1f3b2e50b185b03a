"""The panel plan: a scenario and a feedback variant resolved once into who answers how."""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.errors import AmuledError, ClusterDefinitionError, ScenarioError
from amuled_ma.records.variants import parse_feedback
from amuled_ma.scenario import AGENT_SPECS, MORAL_AGENT, Scenario
from amuled_ma.scenario.agents import match_agents
from amuled_ma.scenario.messages import did_you_mean
from amuled_ma.scenario.panel_weights import weights_prior
from amuled_ma.scenario.paths import find_recording
from amuled_ma.tasks.names import TASK_NAMES

if TYPE_CHECKING:  # loaded by the functions that use them (a plan is made before any read)
    from amuled_ma.beliefs.sources.replay import Recording
    from amuled_ma.clusters import Cluster, ClusterRegistry
    from amuled_ma.scenario import DistillConfig, FeedbackConfig
    from amuled_ma.scenario.agents import AgentSpec

#: What every label of a ``rules`` source says: it answers with the task's rule.
RULES_NOTE = ", the task's rule: the cluster's text is not read"


@dataclass(frozen=True)
class SourcePlan:
    """What `make_source` builds for some agents: its kind, keyword arguments and message label."""

    kind: str
    options: dict[str, Any]
    label: str

    @property
    def key(self) -> str:
        """Canonical JSON of kind and options: equal keys build one shared source."""
        return json.dumps([self.kind, self.options], sort_keys=True, default=str)


@dataclass(frozen=True)
class PanelPlan:
    """A feedback variant resolved from a scenario: everything building it needs.

    ``routes``: the sources of members with their own table, ``default``: of the others;
    ``problems``: ``[(error, label)]`` of sources not planned; ``miss_zero``: a state every
    member missed rewards 0; ``prior``: ``[feedback].weights`` (``amuled`` only, sum 1).
    """

    variant: str
    kind: str
    task: str
    where: str
    seed: int
    clusters: tuple[Any, ...] = ()
    registry: ClusterRegistry | None = None
    rule: str = ""
    routes: dict[str, SourcePlan] = field(default_factory=dict)
    default: SourcePlan | None = None
    problems: tuple[tuple[BaseException, str], ...] = ()
    fused_recording: Path | None = None
    miss_policy: str = "uniform"
    miss_zero: bool = False
    distill: DistillConfig | None = None
    max_abstention: float | None = None
    prior: tuple[float, ...] | None = None

    @property
    def asks_panel(self) -> bool:
        """Whether the feedback is a panel's (not the demonstrator or the human rule)."""
        return self.kind != "human"

    @property
    def agents(self) -> list[str]:
        """The members' names, in panel order."""
        return [c.name for c in self.clusters]

    def source_of(self, agent: str) -> SourcePlan | None:
        """The source answering ``agent`` (None: the fused-only recording, or no panel)."""
        return self.routes.get(agent, self.default)


def cluster_registry(feedback: FeedbackConfig, resolve: Callable[[str], Path]) -> ClusterRegistry:
    """The shipped clusters plus ``[feedback].clusters_dirs`` (later win), resolved by ``resolve``.

    Raises:
        ClusterDefinitionError: A folder is missing or a file is malformed or collides.
    """
    return _registry_cached(tuple(str(resolve(d)) for d in feedback.clusters_dirs))


@functools.lru_cache(maxsize=8)
def _registry_cached(dirs: tuple[str, ...]) -> ClusterRegistry:
    from amuled_ma.clusters import ClusterRegistry

    return ClusterRegistry.load(list(dirs))


def panel_of(
    variant: str, feedback: FeedbackConfig, registry: ClusterRegistry
) -> tuple[list[Cluster], str]:
    """``(clusters, fusion rule)`` of a feedback variant (``amuled``, ``cluster:care``, ...).

    Raises:
        ClusterDefinitionError: A named cluster is in no loaded cluster file.
    """
    kind, arg = parse_feedback(variant)
    names, rule = list(feedback.clusters), feedback.fusion
    if kind == "cluster" and arg:
        names, rule = [arg], "mean"
    elif kind == "moral":
        names, rule = [MORAL_AGENT], "mean"
    elif kind == "agg" and arg:
        rule = arg
    clusters = []
    for name in names:
        if name not in registry:
            dirs = ", ".join(feedback.clusters_dirs) or "none"
            raise ClusterDefinitionError(
                f"feedback {variant!r}: no moral cluster {name!r}"
                f"{did_you_mean(name, list(registry.names()))} in the shipped cluster files "
                f"or the user folders ({dirs}); known: {', '.join(registry.names())}; put its "
                "TOML file in a folder and pass --clusters-dir FOLDER (docs/clusters.md)"
            )
        clusters.append(registry.get(name))
    return clusters, rule


def default_source(
    feedback: FeedbackConfig, resolve: Callable[[str], Path], where: str
) -> SourcePlan:
    """The plan of ``[feedback].source`` (what every agent without a table uses).

    Raises:
        ScenarioError: The replayed recording is not found.
    """
    fb = feedback
    model = AGENT_SPECS.get(fb.source)  # a kind registered at run time takes no options
    spec = model.model_validate({"source": fb.source}) if model is not None else None
    options = spec.source_options(fb, resolve, where, "[feedback]") if spec is not None else {}
    note = f" ({RULES_NOTE.removeprefix(', ')})" if fb.source == "rules" else ""
    return SourcePlan(fb.source, options, f"[feedback].source = {fb.source!r}{note}")


def agent_source(
    feedback: FeedbackConfig,
    resolve: Callable[[str], Path],
    where: str,
    name: str,
    spec: AgentSpec,
    file: str | None = None,
) -> SourcePlan:
    """The plan of agent ``name``'s ``spec``; ``file``: the cluster file the table is from.

    Raises:
        ScenarioError: The agent's recording is not found.
    """
    head = f"{file}: [source]" if file else f"[feedback.agents.{name}]"
    options = spec.source_options(feedback, resolve, where, head)
    detail = spec.detail(options) + (RULES_NOTE if spec.source == "rules" else "")
    return SourcePlan(spec.source, options, f"{head} (source {spec.source!r}{detail})")


def plan_sources(
    feedback: FeedbackConfig,
    resolve: Callable[[str], Path],
    where: str,
    agents: Sequence[str | Cluster],
    files: Mapping[str, str] | None = None,
) -> tuple[dict[str, SourcePlan], SourcePlan | None, list[tuple[BaseException, str]]]:
    """Each panel agent's source: ``(routes, default, problems)`` as in `PanelPlan`.

    ``files``: the tables that came from a cluster file, by that file.
    """
    tables = dict(feedback.agents)
    matched = match_agents(list(tables), agents)
    routes: dict[str, SourcePlan] = {}
    problems: list[tuple[BaseException, str]] = []
    files = files or {}
    for agent, table in matched.items():
        try:
            routes[agent] = agent_source(
                feedback, resolve, where, table, tables[table], files.get(table)
            )
        except AmuledError as error:
            kind = tables[table].source
            head = f"{files[table]}: [source]" if table in files else f"[feedback.agents.{table}]"
            problems.append((error, f"{head} (source {kind!r})"))
    default = None
    others = [a for a in agents if (a if isinstance(a, str) else a.name) not in matched]
    names = ", ".join(a if isinstance(a, str) else a.name for a in others)
    if others:
        try:
            default = default_source(feedback, resolve, where)
            default = dataclasses.replace(default, label=f"{default.label} (agents {names})")
        except AmuledError as error:
            problems.append((error, f"[feedback].source = {feedback.source!r} (agents {names})"))
    if default is not None and default.kind == "rules":
        from amuled_ma.files.resources import prompts_dir

        shipped = (prompts_dir() / "clusters").resolve()
        users = [
            a.name
            for a in others
            if not isinstance(a, str) and a.path and Path(a.path).resolve().parent != shipped
        ]
        if users:
            quoted = ", ".join(f'"{a}"' for a in users)
            table = users[0] if len(users) == 1 else "<name>"
            why = (
                f"the rules source answers every agent with the task's rule and never reads a "
                f"cluster's text, so it does not stand in for your cluster {quoted} by default; "
                f'ask for it by name ([feedback.agents.{table}] source = "rules": the rule '
                "answers, the text is not read), or give it a live model or a person on a "
                'budget ([feedback.agents.<name>] source = "ollama" or "terminal", with '
                "[feedback.distill]; docs/clusters.md)"
            )
            problems.append((ScenarioError(why), default.label))
    return routes, default, problems


class NoHumanRule(ScenarioError):
    """A ``rules`` source asked for the synthetic human on a task that has none."""


def plan_panel(variant: str, scenario: Scenario) -> PanelPlan:
    """Resolve a feedback variant (``amuled``, ``human:rules``, ``cluster:care``, ...) once.

    Sources are not built, nothing is asked and no file is written.

    Raises:
        ClusterDefinitionError: A member is in no loaded cluster file.
        ScenarioError: A fused-only recording asked for another variant or fusion rule, or
            with ``[feedback].weights``; a weights file that is bad or weighs other members.
    """
    kind, arg = parse_feedback(variant)
    fb = scenario.feedback
    base = PanelPlan(
        variant=variant,
        kind=kind,
        task=scenario.task.name,
        where=str(scenario.path or scenario.name),
        seed=scenario.task.seed,
        miss_policy=fb.miss_policy,
        distill=fb.distill,
        max_abstention=fb.max_abstention,
    )
    if kind == "human":
        return dataclasses.replace(base, variant="human:rules" if arg == "rules" else variant)
    registry = cluster_registry(fb, scenario.resolve)
    clusters, rule = panel_of(variant, fb, registry)
    # a cluster file's [source] serves a member without its own table in the scenario
    named = match_agents(list(fb.agents), clusters)
    own = [c for c in clusters if c.source and c.name not in named]
    files = {c.name: str(c.path) for c in own if c.path}
    if own:
        defaults = {c.name: dict(c.source or {}) for c in own}
        scenario = scenario.replace("feedback", agents={**defaults, **fb.agents})
    where = str(scenario.path or f"scenario {scenario.name!r}")
    fused = None
    if scenario.feedback.source == "replay":
        path = find_recording(
            scenario.feedback.recording, scenario.resolve, where=where, required=True
        )
        if recording_of(path).fused_only and not match_agents(
            list(scenario.feedback.agents), clusters
        ):
            fused = path  # (agents with their own source: a panel, the preflight refuses replay)
    base = dataclasses.replace(base, clusters=tuple(clusters), registry=registry, rule=rule)
    if kind == "amuled" and fb.weights.strip():
        if fused is not None:
            raise ScenarioError(
                f"{base.where}: key [feedback].weights: {fused} keeps only the authors' fused "
                "belief per state, so there are no members' beliefs to weigh; replay a "
                'recording with per-cluster beliefs (e.g. recording = "driving-llama-3_1-70b") '
                "or drop weights"
            )
        prior = weights_prior(fb.weights, base.agents, scenario.resolve, base.where)
        base = dataclasses.replace(base, prior=prior)
    if fused is not None:
        if kind != "amuled" or fb.fusion != "bjs-dst":
            raise ScenarioError(
                f"{fused} keeps only the authors' fused belief per state ('beliefs': null), so "
                f"it can serve the amuled variant (bjs-dst) only, not {variant!r} with fusion "
                f"{fb.fusion!r}; use a recording with per-cluster beliefs, e.g. "
                'recording = "driving-llama-3_1-70b"'
            )
        return dataclasses.replace(base, fused_recording=fused)
    routes, default, problems = plan_sources(
        scenario.feedback, scenario.resolve, where, clusters, files
    )
    plans = [p for p in [*routes.values(), default] if p is not None]
    human = [p for p in plans if p.kind == "rules" and p.options["policy"] == "human"]
    if human and scenario.task.name not in TASK_NAMES:  # the paper's tasks have one
        from amuled_ma.tasks import get_task  # here: it imports torch

        task_class = get_task(scenario.task.name)
        if not task_class.human_feedback:
            judges = ", ".join(f'"judge:{j}"' for j in task_class.judge_names) or "none"
            error = NoHumanRule(
                f"the rules source's policy 'human' is the synthetic human feedback of a task "
                f"that has one (the paper's two); task {scenario.task.name!r} has none, so it "
                f"would answer no state; give the agent one of the task's judges (policy = one "
                f"of {judges}), or a live model or a person ([feedback.agents.<name>] source = "
                '"ollama" or "terminal"; docs/clusters.md)'
            )
            problems += [(error, p.label) for p in human]
    return dataclasses.replace(
        base,
        routes=routes,
        default=default,
        problems=tuple(problems),
        miss_zero=any(p.kind == "replay" for p in plans) and fb.miss_policy == "zero",
    )


def recording_of(path: Path) -> Recording:
    """The `Recording` at ``path``, read once per version."""
    return _recording_cached(str(path), path.stat().st_mtime_ns)


@functools.lru_cache(maxsize=4)
def _recording_cached(path: str, mtime_ns: int) -> Recording:
    from amuled_ma.beliefs.sources.replay import Recording

    return Recording(path)
