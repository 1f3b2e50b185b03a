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
from amuled_ma.scenario.loading import weights_prior
from amuled_ma.scenario.messages import did_you_mean
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
    weights_file: Path | None = None

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

    def describe(self) -> dict[str, Any]:
        """The plan as plain JSON: members and sources, rule, recording, fused-only, weights."""
        if not self.asks_panel:
            source = "rules" if self.variant == "human:rules" else "demonstrator"
            return {
                "feedback": self.variant,
                "members": [{"agent": self.variant, "source": source, "label": source}],
                "fusion": None,
                "recording": None,
                "fused_only": False,
                "distill": False,
            }
        recordings = []
        members = []
        for agent in self.agents:
            plan = self.source_of(agent)
            if plan is None:
                kind, label = "replay", "fused-only recording"
            else:
                kind, label = plan.kind, plan.label
                if plan.kind == "replay":
                    recordings.append(Path(plan.options["paths"]).name)
            members.append({"agent": agent, "source": kind, "label": label})
        if self.fused_recording is not None:
            recordings = [self.fused_recording.name]
        described: dict[str, Any] = {
            "feedback": self.variant,
            "members": members,
            "fusion": self.rule,
            "recording": recordings[0] if recordings else None,
            "fused_only": self.fused_recording is not None,
            "distill": bool(self.distill is not None and self.distill.enabled),
        }
        if self.prior is not None:
            described["weights"] = {
                "file": self.weights_file.name if self.weights_file is not None else None,
                "prior": dict(zip(self.agents, self.prior, strict=True)),
            }
        return described


def cluster_registry(feedback: FeedbackConfig, resolve: Callable[[str], Path]) -> ClusterRegistry:
    """The shipped clusters plus ``[feedback].clusters_dirs`` (later win), resolved by ``resolve``.

    Raises:
        ClusterDefinitionError: A folder is missing or a file is malformed or collides.
    """
    dirs = [resolve(d) for d in feedback.clusters_dirs]
    return _registry_cached(tuple(str(d) for d in dirs))


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


def cluster_tables(
    agents: Mapping[str, AgentSpec], clusters: Sequence[Cluster]
) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """Each cluster file's ``[source]`` for a member without its own agent table, and its file.

    Returns ``({cluster name: its [source] table}, {cluster name: its file})``; the tables
    merge under ``[feedback.agents]`` (the scenario's own table for an agent wins).
    """
    named = match_agents(list(agents), clusters)
    own = {c.name: c for c in clusters if c.source and c.name not in named}
    tables = {name: dict(c.source or {}) for name, c in own.items()}
    return tables, {name: str(c.path) for name, c in own.items() if c.path}


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

    ``files``: the tables that came from a cluster file (`cluster_tables`), by that file.
    """
    tables = dict(feedback.agents)
    matched = match_agents(list(tables), agents)
    names = [a if isinstance(a, str) else a.name for a in agents]
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
    others = [a for a in names if a not in matched]
    if others:
        try:
            default = default_source(feedback, resolve, where)
            default = dataclasses.replace(
                default, label=f"{default.label} (agents {', '.join(others)})"
            )
        except AmuledError as error:
            label = f"[feedback].source = {feedback.source!r}"
            problems.append((error, f"{label} (agents {', '.join(others)})"))
    if default is not None and default.kind == "rules":
        users = user_clusters([a for a in agents if not isinstance(a, str) and a.name in others])
        if users:
            problems.append((ScenarioError(rules_by_name(users)), default.label))
    return routes, default, problems


def user_clusters(clusters: Sequence[Any]) -> list[str]:
    """The names of the clusters read from a user's folder (not a shipped cluster file)."""
    from amuled_ma.files.resources import prompts_dir

    shipped = (prompts_dir() / "clusters").resolve()
    out = []
    for cluster in clusters:
        path = getattr(cluster, "path", None)
        if path is not None and Path(path).resolve().parent != shipped:
            out.append(cluster.name)
    return out


def rules_by_name(agents: Sequence[str]) -> str:
    """Why ``[feedback].source = "rules"`` does not answer for a user's text cluster."""
    names = ", ".join(f'"{a}"' for a in agents)
    table = agents[0] if len(agents) == 1 else "<name>"
    return (
        f"the rules source answers every agent with the task's rule and never reads a "
        f"cluster's text, so it does not stand in for your cluster {names} by default; ask "
        f'for it by name ([feedback.agents.{table}] source = "rules": the rule answers, '
        "the text is not read), or give it a live model or a person on a budget "
        '([feedback.agents.<name>] source = "ollama" or "terminal", with [feedback.distill]; '
        "docs/clusters.md)"
    )


class NoHumanRule(ScenarioError):
    """A ``rules`` source asked for the synthetic human on a task that has none."""


def _no_human_rule(
    task: str, plans: Sequence[SourcePlan | None]
) -> list[tuple[BaseException, str]]:
    """The ``rules`` sources with policy ``human`` when ``task`` has no synthetic human."""
    human = [
        p for p in plans if p is not None and p.kind == "rules" and p.options["policy"] == "human"
    ]
    if not human or task in TASK_NAMES:  # the paper's tasks have it (no import of the task)
        return []
    from amuled_ma.tasks import get_task  # here: it imports torch

    task_class = get_task(task)
    if task_class.human_feedback:
        return []
    judges = ", ".join(f'"judge:{j}"' for j in task_class.judge_names) or "none"
    error = NoHumanRule(
        f"the rules source's policy 'human' is the synthetic human feedback of a task that "
        f"has one (the paper's two); task {task!r} has none, so it would answer no state; give "
        f"the agent one of the task's judges (policy = one of {judges}), or a live model or a "
        'person ([feedback.agents.<name>] source = "ollama" or "terminal"; docs/clusters.md)'
    )
    return [(error, p.label) for p in human]


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
    defaults, files = cluster_tables(fb.agents, clusters)
    if defaults:
        scenario = scenario.replace("feedback", agents={**defaults, **fb.agents})
    where = str(scenario.path or f"scenario {scenario.name!r}")
    fused = _fused_only_recording(scenario.feedback, scenario.resolve, where)
    if fused is not None and match_agents(list(scenario.feedback.agents), clusters):
        fused = None  # agents with their own source: a panel (the preflight refuses replay)
    base = dataclasses.replace(base, clusters=tuple(clusters), registry=registry, rule=rule)
    if kind == "amuled" and fb.weights.strip():
        if fused is not None:
            raise ScenarioError(
                f"{base.where}: key [feedback].weights: {fused} keeps only the authors' fused "
                "belief per state, so there are no members' beliefs to weigh; replay a "
                'recording with per-cluster beliefs (e.g. recording = "driving-llama-3_1-70b") '
                "or drop weights"
            )
        weighted = weights_prior(fb.weights, base.agents, scenario.resolve, base.where)
        base = dataclasses.replace(base, prior=weighted[0], weights_file=weighted[1])
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
    problems += _no_human_rule(scenario.task.name, [*routes.values(), default])
    replays = any(p.kind == "replay" for p in [*routes.values(), default] if p is not None)
    return dataclasses.replace(
        base,
        routes=routes,
        default=default,
        problems=tuple(problems),
        miss_zero=replays and fb.miss_policy == "zero",
    )


def _fused_only_recording(
    feedback: FeedbackConfig, resolve: Callable[[str], Path], where: str
) -> Path | None:
    """``[feedback].recording`` when it is replayed and holds only fused beliefs, else None.

    Raises:
        ScenarioError: The recording is not found.
    """
    if feedback.source != "replay":
        return None
    path = find_recording(feedback.recording, resolve, where=where, required=True)
    return path if recording_of(path).fused_only else None


def recording_of(path: Path) -> Recording:
    """The `Recording` at ``path``, read once per version."""
    return _recording_cached(str(path), path.stat().st_mtime_ns)


@functools.lru_cache(maxsize=4)
def _recording_cached(path: str, mtime_ns: int) -> Recording:
    from amuled_ma.beliefs.sources.replay import Recording

    return Recording(path)
