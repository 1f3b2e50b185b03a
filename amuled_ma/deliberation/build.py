"""Feedback built from a panel plan behind a given belief store; the plan's preflight."""

from __future__ import annotations

import contextlib
import functools
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from amuled_ma.beliefs.sources.registry import make_source as build_source
from amuled_ma.beliefs.sources.replay import ReplaySource
from amuled_ma.beliefs.sources.routing import RoutedSource
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.store.service import StoreItem, StoreService
from amuled_ma.beliefs.types import BeliefResult, BeliefSource
from amuled_ma.deliberation.plan import PanelPlan, SourcePlan, recording_of
from amuled_ma.errors import AmuledError, ScenarioError
from amuled_ma.scenario.agents import AGENT_SOURCE_KINDS, norm

if TYPE_CHECKING:  # the feedback classes import torch: loaded when a feedback is built,
    # so that the preflight's errors come before any heavy import
    from amuled_ma.deliberation.feedback_base import Feedback
    from amuled_ma.scenario import DistillConfig

#: The ways to give a member beliefs, named in the preflight's messages.
_KINDS = " | ".join(f'"{k}"' for k in AGENT_SOURCE_KINDS if k != "replay")
#: The distinct states a budget asks in the preflight's suggestion
#: (``[feedback.distill].budget``, an integer: that many states; docs/distill.md).
SUGGESTED_BUDGET = 20


#: Seconds per request of the private tiny Ollama model in the docs (docs/ollama.md, "Where a
#: request's time goes"), quoted as such when the store has too few timed requests.
TINY_SECONDS_PER_REQUEST = 4.1
#: Recorded requests a median needs before it stands for this machine's cost per request.
MIN_TIMED_REQUESTS = 5


class RequestCost(NamedTuple):
    """Seconds per live request to a model, and where the figure comes from (in words)."""

    seconds: float
    basis: str


def request_cost(store: Path | None, model: str) -> RequestCost:
    """One request to ``model``: the store's median seconds, else `TINY_SECONDS_PER_REQUEST`."""
    if store is not None and Path(store).is_file():
        with BeliefStore(store, read_only=True) as held:
            seconds = held.request_seconds(model)
        if len(seconds) >= MIN_TIMED_REQUESTS:
            return RequestCost(
                float(np.median(seconds)),
                f"measured here: median of {len(seconds)} recorded requests",
            )
    return RequestCost(
        TINY_SECONDS_PER_REQUEST, "the docs' figure for the tiny model, not measured here"
    )


#: A cached probe per (model, options): one per process, however many jobs plan the model.
_PROBED: dict[str, RequestCost] = {}


def probe_cost(source: Any, plan: PanelPlan, agent: str) -> RequestCost:
    """Time one live request to ``source`` after a warm-up; nothing is stored.

    The warm-up loads the model and fills the server's prompt cache, as a run's first requests
    do. A failed request gives the docs' figure.
    """
    import torch

    from amuled_ma.beliefs.types import BeliefRequest
    from amuled_ma.clusters import build_messages
    from amuled_ma.deliberation.panel import MoralPanel
    from amuled_ma.tasks import make_batched

    cluster = next(c for c in plan.clusters if c.name == agent)
    panel = MoralPanel(
        plan.task,
        [cluster],
        source,
        plan.rule,
        build_messages=functools.partial(build_messages, registry=plan.registry),
    )
    task = make_batched(plan.task, 1, seed=plan.seed)
    task.reset()
    states = [(task.obs[0].tolist(), task.prompt_variables([0])[0])]
    for action in range(panel.num_actions):  # the first action that changes the state
        task.step(torch.tensor([action]))
        if task.obs[0].tolist() != states[0][0]:
            break
    states.append((task.obs[0].tolist(), task.prompt_variables([0])[0]))
    seconds = 0.0
    for obs, variables in states:
        request = BeliefRequest(
            plan.task,
            agent,
            tuple(float(x) for x in obs),
            panel.action_names,
            panel.messages(0, panel.state_prompt(variables)),
        )
        start = time.perf_counter()
        (result,) = source.beliefs([request])
        seconds = time.perf_counter() - start
        if result.status not in ("ok", "repaired"):
            reason = (result.extra or {}).get("error") or result.status
            return RequestCost(
                TINY_SECONDS_PER_REQUEST,
                f"not measured: the probe failed ({str(reason)[:80]}); the docs' figure",
            )
    return RequestCost(seconds, "measured here: 1 request timed after a warm-up")


def live_costs(plan: PanelPlan, store: Path, say: Callable[[str], None] | None = None) -> list[str]:
    """One line per live (Ollama) member source of a fine-tune's panel: its cost per request, total.

    The cost is `request_cost`, else `probe_cost` (once per model and options in this process;
    ``say`` is told first). Raises as `build_members`.
    """
    if not plan.asks_panel or plan.fused_recording is not None:
        return []
    specs = [*([plan.default] if plan.default is not None else []), *plan.routes.values()]
    served: dict[str, list[str]] = {spec.key: [] for spec in specs if spec.kind == "ollama"}
    if not served:
        return []
    for agent in plan.agents:  # the agents of each distinct Ollama source
        spec = plan.source_of(agent)
        if spec is not None and spec.key in served:
            served[spec.key].append(agent)
    members = build_members(plan)
    try:
        lines = []
        budget = plan.distill.budget if plan.distill is not None and plan.distill.enabled else None
        for key, agents in served.items():
            if not agents:
                continue
            spec = plan.source_of(agents[0])
            assert spec is not None
            source = members.routes.get(agents[0], members.default)
            model = str(spec.options.get("model", getattr(source, "model", "")))
            cost = request_cost(store, model)
            if not cost.basis.startswith("measured here"):
                if key not in _PROBED:
                    if say is not None:
                        say(
                            f"live feedback: timing a request to {model} here (the belief store "
                            f"holds fewer than {MIN_TIMED_REQUESTS} timed requests) ..."
                        )
                    _PROBED[key] = probe_cost(source, plan, agents[0])
                cost = _PROBED[key]
            per = f"{cost.seconds:.1f} s a request ({cost.basis})"
            who = f"{', '.join(agents)} asked of {model}"
            if isinstance(budget, int) and not isinstance(budget, bool):
                asks = budget * len(agents)
                lines.append(
                    f"live feedback: {who}: {per} x {asks:,} requests on the budget "
                    f"({budget:,} states) = ~{asks * cost.seconds:,.0f} s"
                )
            else:
                lines.append(
                    f"live feedback: {who}: {per} x {len(agents)} per new state the fine-tune "
                    "visits (no integer budget: the total is not known ahead)"
                )
        return lines
    finally:
        members.close()


def _replay_problem(
    source: ReplaySource, agents: Sequence[str], task: str, distill: DistillConfig | None = None
) -> str | None:
    """Why a replay source cannot answer ``agents`` on ``task`` (from its recordings)."""
    recordings = list(source.recordings)
    fused_only = [r for r in recordings if r.fused_only]
    if fused_only:
        return (
            f"{fused_only[0].path} keeps only the authors' fused belief per state "
            "('beliefs': null), so it cannot answer per agent; name a recording "
            'with per-cluster beliefs (e.g. recording = "driving-llama-3_1-70b")'
        )
    matching = [r for r in recordings if norm(r.task) == norm(task)]
    if not matching:
        held = ", ".join(f"{r.path.stem} (task {r.task!r})" for r in recordings)
        return (
            f"no recording of task {task!r}: {held}; replay a recording of {task} "
            f"([feedback].recording), or give the members beliefs with "
            f"[feedback.agents.<name>] source = {_KINDS}"
        )
    recording = matching[0]
    missing = [a for a in agents if source.recording_agent(recording, a) is None]
    if not missing:
        return None
    names = ", ".join(f'"{a}"' for a in missing)
    n, states = len(missing), len(recording.states)
    what = f"cluster {names} is" if n == 1 else f"clusters {names} are"
    budget = SUGGESTED_BUDGET
    if distill is not None and distill.enabled:
        value = distill.budget
        budget = int(value) if isinstance(value, int) else max(1, int(value * states))
    tables = ",".join(f'{m}={{source="terminal"}}' for m in missing)
    them = "it" if n == 1 else "them"
    return (
        f"{what} not in recording {recording.path.stem} (it holds: "
        f"{', '.join(recording.clusters)}); answer {them} at the terminal with --set "
        f"'feedback.agents={{{tables}}}' ({states * n:,} answers, or {budget * n:,} with --set "
        f"feedback.distill.enabled=true), or drop {them} from feedback.clusters; a live model "
        "and other sources: docs/clusters.md#a-cluster-no-recording-holds"
    )


class Members(NamedTuple):
    """A plan's member sources, each distinct one built once, checked and open.

    ``routes`` and ``default`` as in `PanelPlan`; ``plans`` maps ``id(source)`` to its plan.
    """

    routes: dict[str, BeliefSource]
    default: BeliefSource | None
    plans: dict[int, SourcePlan]

    def close(self) -> None:
        """Close every distinct source once."""
        sources = [*self.routes.values(), *([self.default] if self.default is not None else [])]
        for source in {id(source): source for source in sources}.values():
            source.close()


def build_members(plan: PanelPlan, *, build: Callable[..., BeliefSource] = build_source) -> Members:
    """Build and check every distinct member source of a plan once (equal plans share one).

    Raises:
        AmuledError: One problem: its own class, prefixed with the agent and source; several:
            a `ScenarioError` listing each. Every source built is closed first.
    """
    where = plan.where
    default = plan.default
    distinct: dict[str, tuple[SourcePlan, list[str]]] = {}
    if default is not None:
        distinct[default.key] = (default, [])
    for agent, spec in plan.routes.items():
        distinct.setdefault(spec.key, (spec, []))[1].append(agent)
    served: dict[str, list[str]] = {key: [] for key in distinct}
    for agent in plan.agents:
        planned = plan.source_of(agent)
        if planned is not None:
            served[planned.key].append(agent)
    built: dict[str, BeliefSource] = {}
    problems = list(plan.problems)
    for key, (spec, agents) in distinct.items():
        label = spec.label
        if spec is default and agents:
            label = f"{label}, also {', '.join(f'[feedback.agents.{a}]' for a in agents)}"
        elif len(agents) > 1:
            label = f"{label} (shared by agents {', '.join(agents)})"
        try:
            source = build(spec.kind, **json.loads(json.dumps(spec.options)))
        except Exception as error:
            problems.append((error, label))
            continue
        built[key] = source
        try:
            check = getattr(source, "check", None)
            if callable(check):
                check()
            if spec.kind == "replay" and isinstance(source, ReplaySource):
                problem = _replay_problem(source, served[key], plan.task, plan.distill)
                if problem:
                    raise ScenarioError(problem)
        except Exception as error:
            problems.append((error, label))
    if problems:
        for source in built.values():
            with contextlib.suppress(Exception):  # the preflight error matters more
                source.close()
        if len(problems) == 1:
            first, label = problems[0]
            # a label names a key of the scenario ("[feedback.agents.care] ..."), or the
            # cluster file that holds the table ("clusters/care.toml: [source] ...")
            place = f"{where}: " if label.startswith("[") else ""
            text = f"{place}{label}: {str(first).removeprefix(f'{where}: ')}"
            wrapped: BaseException = ScenarioError(text)
            if isinstance(first, AmuledError):
                with contextlib.suppress(TypeError):  # an error class with another signature
                    wrapped = type(first)(text)
            raise wrapped from first
        lines = "\n".join(
            f"  - {label}: {str(e).removeprefix(f'{where}: ')}" for e, label in problems
        )
        raise ScenarioError(
            f"{where}: {len(problems)} belief sources of the panel cannot be used; fix each "
            f"before training:\n{lines}"
        ) from problems[0][0]
    routes = {agent: built[spec.key] for agent, spec in plan.routes.items()}
    plans = {id(built[k]): spec for k, (spec, _) in distinct.items()}
    return Members(routes, built[default.key] if default is not None else None, plans)


def preflight(plan: PanelPlan) -> None:
    """Check that every member of a plan can answer, before any work (else `AmuledError`)."""
    members = checked_members(plan)
    if members is not None:
        members.close()


def checked_members(plan: PanelPlan) -> Members | None:
    """The preflight of a plan (raising as `preflight`), its member sources kept open.

    None when the feedback asks no member source; else the caller owns the members.
    """
    if not plan.asks_panel:
        return None
    if plan.fused_recording is not None:
        recording = recording_of(plan.fused_recording)
        if norm(recording.task) != norm(plan.task):
            raise ScenarioError(
                f"{plan.where}: [feedback].recording {recording.path.stem} is of task "
                f"{recording.task!r}, not {plan.task!r}; replay a recording of {plan.task}"
            )
        check_distillable(plan)
        return None
    return build_members(plan)


def check_distillable(plan: PanelPlan) -> None:
    """Refuse ``[feedback.distill]`` on a recording of fused beliefs only (`ScenarioError`)."""
    if plan.fused_recording is None or plan.distill is None or not plan.distill.enabled:
        return
    raise ScenarioError(
        f"{plan.fused_recording} keeps only the authors' fused belief per state ('beliefs': "
        "null), so [feedback.distill] cannot learn each panel member's belief from it; replay "
        'a recording with per-cluster beliefs (--set feedback.recording="driving-llama-3_1-70b") '
        "or turn distillation off (--set feedback.distill.enabled=false)"
    )


def panel_source(
    plan: PanelPlan, store: StoreService, members: Members | None = None
) -> CachedSource | RoutedSource:
    """The belief source of a plan's panel, members behind ``store`` (raises as `build_members`).

    One ``CachedSource`` when every member shares one source, else a ``RoutedSource``.
    """
    routes, default, plans = members if members is not None else build_members(plan)
    if not routes:
        assert default is not None
        return CachedSource(default, store)
    cached: dict[int, CachedSource] = {}

    def wrap(source: BeliefSource) -> CachedSource:
        if id(source) not in cached:
            spec = plans[id(source)]
            identity = None
            if spec.kind == "entry-point":
                # a plug-in's own identity may be the bare default ({"source": name}):
                # the entry point and its options keep two plug-ins' answers apart
                identity = {"source": "entry-point", **spec.options, "plugin": source.identity()}
            cached[id(source)] = CachedSource(source, store, identity=identity)
        return cached[id(source)]

    return RoutedSource(
        {agent: wrap(source) for agent, source in routes.items()},
        wrap(default) if default is not None else None,
    )


def build_feedback(
    plan: PanelPlan,
    store: StoreService,
    *,
    members: Members | None = None,
    state_dir: Path | None = None,
    resume: bool = False,
    seed: int | None = None,
    cache_dir: Path | None = None,
) -> Feedback:
    """Build the feedback of a plan, its panel's members behind ``store`` (the caller owns it).

    ``members`` from `checked_members` are handed over (default: built here). With
    ``[feedback.distill].enabled`` the panel is distilled in ``state_dir`` (``resume`` continues
    its budget); ``seed`` seeds the distilled model unless ``[feedback.distill].seed`` is set.

    Raises:
        AmuledError: A member's source cannot be built or checked.
    """
    from amuled_ma.deliberation.feedback_base import CallableFeedback, DemonstratorFeedback
    from amuled_ma.deliberation.panel_feedback import FusedReplayFeedback, PanelFeedback

    if plan.variant == "human:rules":
        from amuled_ma.tasks.human import human_belief

        task = plan.task
        feedback: Feedback = CallableFeedback(
            lambda obs: np.asarray(human_belief(task, obs)).reshape(len(obs), -1),
            name="human:rules",
        )
    elif not plan.asks_panel:
        feedback = DemonstratorFeedback(plan.task, seed=plan.seed, cache_dir=cache_dir)
    elif plan.fused_recording is not None:
        check_distillable(plan)
        feedback = FusedReplayFeedback(recording_of(plan.fused_recording), plan.miss_policy)
    else:
        from amuled_ma.clusters import build_messages
        from amuled_ma.deliberation.panel import MoralPanel

        source: BeliefSource = panel_source(plan, store, members)
        if plan.distill is not None and plan.distill.enabled and state_dir is not None:
            from amuled_ma.distill import DistilledSource

            try:
                source = DistilledSource.from_config(
                    source,
                    plan.distill,
                    seed=plan.seed if seed is None else seed,
                    fusion_rule=plan.rule,
                    state_dir=state_dir,
                    resume=resume,
                )
            except BaseException:
                source.close()
                raise
            _count_questions(source, plan)
        panel = MoralPanel(
            plan.task,
            list(plan.clusters),
            source,
            plan.rule,
            build_messages=functools.partial(build_messages, registry=plan.registry),
            prior=plan.prior,
        )
        feedback = PanelFeedback(plan.variant, panel, source, miss_zero=plan.miss_zero)
    if plan.asks_panel:  # the demonstrator and the human rule always answer
        feedback.max_abstention = plan.max_abstention
    feedback.plan = plan
    return feedback


def _count_questions(distilled: Any, plan: PanelPlan) -> None:
    """Tell each person at the terminal the questions ahead on an integer budget.

    A person answering for ``m`` agents is asked ``(budget - states already asked) x m``.
    """
    from amuled_ma.beliefs.sources.terminal import TerminalSource

    budget = plan.distill.budget if plan.distill is not None else None
    if not isinstance(budget, int):
        return
    states = max(0, budget - distilled.ledger.asked_count)
    panel = distilled.source
    served: dict[int, tuple[TerminalSource, int]] = {}
    for cluster in plan.clusters:
        member = panel.source_for(cluster.name) if isinstance(panel, RoutedSource) else panel
        if isinstance(member, CachedSource):
            member = member.source
        if isinstance(member, TerminalSource):
            count = served.get(id(member), (member, 0))[1]
            served[id(member)] = (member, count + 1)
    for person, agents in served.values():
        person.expected = states * agents


def run_store(path: Path) -> StoreService:
    """The belief store at ``path``, opened on first use (never, if no member is asked)."""
    return _Lazy(path)


class _Lazy:
    """A store opened on first use: the preflight runs before its file is created."""

    def __init__(self, path: Path) -> None:
        self.path = path

    @functools.cached_property
    def store(self) -> BeliefStore:
        """The store, opened (and created) now."""
        return BeliefStore(self.path)

    def lookup(self, keys: list[str]) -> dict[str, BeliefResult]:
        """The store's ``lookup``."""
        return self.store.lookup(keys)

    def put_many(self, items: Sequence[StoreItem]) -> int:
        """The store's ``put_many``."""
        return self.store.put_many(items)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.store, name)

    def close(self) -> None:
        """Close the store if it was opened."""
        if "store" in self.__dict__:
            self.store.close()
