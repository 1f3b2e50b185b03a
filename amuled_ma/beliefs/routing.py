"""A belief source per panel member: :class:`RoutedSource` and ``[feedback.agents]``.

Each member of a panel (a moral cluster, the unprompted moral agent) may take its
beliefs from its own source: an Ollama model of its own, a person at the terminal, a
rule, a plug-in, a saved torch policy. A scenario says so per agent::

    [feedback.agents.care]
    source = "ollama"
    model = "llama3.1:8b"

    [feedback.agents.human]
    source = "terminal"

:class:`RoutedSource` is one :class:`~amuled_ma.beliefs.types.BeliefSource` over these
members: it splits a batch by ``request.cluster``, sends each member its sub-batch in
**one** call (so each member keeps its own deduplication, batching and concurrency) and
puts the answers back in the batch's order. Members are normally each wrapped in their
own :class:`~amuled_ma.beliefs.cached.CachedSource` over one shared store, so that every
store key holds the identity of the source that answered; members with the same
specification are one shared object.

This module also reads and checks the ``[feedback.agents.<name>]`` tables
(:func:`check_agent_tables`, called by :mod:`amuled_ma.scenario` on load) and turns a
scenario into the specification of each member's source (:func:`panel_specs`,
:func:`build_members`, used by :func:`amuled_ma.deliberation.feedback.make_source`;
:func:`preflight` checks them all without a store). See
``docs/beliefs.md``, section "Per-agent sources".
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.errors import AmuledError, ScenarioError

#: Source kinds a ``[feedback.agents.<name>]`` table may name.
AGENT_SOURCE_KINDS = ("replay", "ollama", "rules", "terminal", "entry-point", "policy")

#: Name of the unprompted moral agent (``cluster:`` variants aside, the ``moral`` variant).
MORAL_AGENT = "moral_agent"

#: Keys of each kind's table besides ``source``: ``{key: (accepted types, what it is)}``.
#: The ``ollama`` kind also takes every keyword of
#: :class:`~amuled_ma.beliefs.ollama.OllamaSource` (see :func:`ollama_keywords`).
AGENT_KEYS: dict[str, dict[str, tuple[tuple[type, ...], str]]] = {
    "replay": {"recording": ((str,), "a recording file or name (default [feedback].recording)")},
    "ollama": {
        "model": ((str,), "an Ollama model name"),
        "host": ((str,), "the Ollama server URL"),
        "hosts": ((list,), "a pool of Ollama server URLs (instead of host)"),
        "concurrency": ((int,), "requests in flight"),
        "timeout_s": ((int, float), "seconds per request"),
    },
    "rules": {"policy": ((str,), "'human' or 'pkg.module:function'")},
    "terminal": {
        "person": ((str,), "who answers (kept apart in the store)"),
        "attempts": ((int,), "answer lines read per state"),
    },
    "entry-point": {
        "name": ((str,), "an installed amuled_ma.agents name or 'pkg.module:Class'"),
        "options": ((dict,), "the plug-in's keyword arguments"),
    },
    "policy": {
        "path": ((str,), "a torch.save state dict, relative to the scenario file"),
        "key": ((str,), "the state dict's key in a checkpoint dict"),
        "module": ((str,), "'pkg.module:Class' of the network"),
        "kwargs": ((dict,), "keyword arguments of module"),
        "activation": ((str,), "activation of an inferred MLP"),
    },
}

#: What each kind's table must hold, and an example for the fix.
_REQUIRED = {
    "ollama": ("model", 'model = "llama3.1:8b" (an Ollama model name)'),
    "entry-point": (
        "name",
        'name = "my_pkg.agents:MyAgent" (or an installed amuled_ma.agents name)',
    ),
    "policy": (
        "path",
        'path = "policies/virtue.pt" (a torch.save state dict, relative to the scenario file)',
    ),
}
#: Type names in messages.
_TYPE_NAMES = {str: "string", int: "integer", float: "float", bool: "boolean", dict: "table",
               list: "array"}  # fmt: skip

#: Declared ranges of a few numbers: ``(key, low, high, low_open, why)``.
_RANGES = {
    "concurrency": (1, 1024, False, "LLM requests in flight, one connection each"),
    "timeout_s": (0, 86_400, True, "seconds per LLM request: 0 fails all, above a day hangs"),
    "attempts": (1, 100, False, "answer lines read per state"),
}

_PLAIN = (str, int, float, bool, list, dict)


def _norm(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


def _found(value: Any) -> str:
    names = {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
             dict: "table"}  # fmt: skip
    return f"{names.get(type(value), type(value).__name__)} ({value!r})"


# ----------------------------------------------------------------------------- routing
class RoutedSource(BeliefSource):
    """Answer each request with the source of its agent (``request.cluster``).

    Args:
        routes: ``{agent name: source}``; the same source object may serve several agents
            (it then gets their requests in one call).
        default: The source of every agent without a route (``None``: such a request is
            an error).

    Raises:
        ValueError: No route and no default.

    """

    name = "routed"

    def __init__(
        self, routes: Mapping[str, BeliefSource], default: BeliefSource | None = None
    ) -> None:
        if not routes and default is None:
            raise ValueError("a routed source needs at least one route or a default source")
        self.routes: dict[str, BeliefSource] = dict(routes)
        self.default = default
        members: dict[int, tuple[BeliefSource, list[str]]] = {}
        for agent, source in self.routes.items():
            members.setdefault(id(source), (source, []))[1].append(agent)
        if default is not None:
            members.setdefault(id(default), (default, []))
        #: The distinct member sources, each with the agents routed to it (the default
        #: source's list holds only agents named in ``routes``).
        self.members: list[tuple[BeliefSource, tuple[str, ...]]] = [
            (source, tuple(agents)) for source, agents in members.values()
        ]

    @property
    def needs_messages(self) -> bool:  # type: ignore[override]
        """True when any member reads ``BeliefRequest.messages``."""
        return any(bool(getattr(s, "needs_messages", True)) for s, _ in self.members)

    def source_for(self, agent: str) -> BeliefSource:
        """Return the source answering ``agent``.

        Raises:
            ScenarioError: No route and no default source.

        """
        source = self.routes.get(agent, self.default)
        if source is None:
            raise ScenarioError(
                f"no belief source for agent {agent!r}: routed agents are "
                f"{', '.join(self.routes)} and there is no default source; add a "
                f"[feedback.agents.{agent}] table or a default [feedback].source"
            )
        return source

    def _split(self, requests: Sequence[BeliefRequest]) -> list[tuple[BeliefSource, list[int]]]:
        """Group request indices by member source, members in order of first request."""
        groups: dict[int, tuple[BeliefSource, list[int]]] = {}
        for i, request in enumerate(requests):
            source = self.source_for(request.cluster)
            groups.setdefault(id(source), (source, []))[1].append(i)
        return list(groups.values())

    @staticmethod
    def _sub_batch(
        source: BeliefSource, requests: Sequence[BeliefRequest], indices: list[int]
    ) -> list[BeliefRequest]:
        """The member's requests; without messages for a member that reads none.

        Dropping the chat for replay, rules and policy members keeps their store keys
        the same as when they serve a whole panel alone (the panel sends no chat then).
        """
        if getattr(source, "needs_messages", True):
            return [requests[i] for i in indices]
        return [
            dataclasses.replace(requests[i], messages=()) if requests[i].messages else requests[i]
            for i in indices
        ]

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Send each member its requests in one call; return the answers in order.

        Args:
            requests: The batch (any mix of agents).

        Returns:
            One result per request, in order.

        Raises:
            ScenarioError: A request's agent has no source.
            RuntimeError: A member answered a different number of results.

        """
        out: list[BeliefResult | None] = [None] * len(requests)
        for source, indices in self._split(requests):
            results = source.beliefs(self._sub_batch(source, requests, indices))
            if len(results) != len(indices):
                raise RuntimeError(
                    f"belief source {getattr(source, 'name', '?')!r} answered {len(results)} "
                    f"results for {len(indices)} requests"
                )
            for i, result in zip(indices, results, strict=True):
                out[i] = result
        return out  # type: ignore[return-value]

    def iter_beliefs(self, requests: Sequence[BeliefRequest]) -> Iterator[tuple[int, BeliefResult]]:
        """Yield ``(index, result)`` member by member, as each member answers.

        A member with ``iter_beliefs`` yields as its answers arrive; any other member's
        answers come after its one call.
        """
        for source, indices in self._split(requests):
            batch = self._sub_batch(source, requests, indices)
            iterate = getattr(source, "iter_beliefs", None)
            if callable(iterate):
                for j, result in iterate(batch):
                    yield indices[j], result
            else:
                for i, result in zip(indices, source.beliefs(batch), strict=True):
                    yield i, result

    def identity(self) -> dict[str, Any]:
        """Describe every member: ``{"routes": {agent: identity}, "default": identity}``."""
        return {
            "source": self.name,
            "routes": {agent: dict(s.identity()) for agent, s in sorted(self.routes.items())},
            "default": dict(self.default.identity()) if self.default is not None else None,
        }

    def close(self) -> None:
        """Close every distinct member once (the first error is raised after all)."""
        first: BaseException | None = None
        for source, _ in self.members:
            try:
                source.close()
            except Exception as error:  # close the others anyway
                first = first or error
        if first is not None:
            raise first


# ------------------------------------------------------------------- [feedback.agents]
def ollama_keywords() -> dict[str, Any]:
    """The keywords of :class:`~amuled_ma.beliefs.ollama.OllamaSource` a scenario may set.

    Returns:
        ``{keyword: default}``, without ``transport`` and ``fallback`` (not TOML values).

    """
    import inspect

    from amuled_ma.beliefs.ollama import OllamaSource

    return {
        name: p.default
        for name, p in inspect.signature(OllamaSource).parameters.items()
        if name not in ("transport", "fallback")
    }


def check_ollama_keys(table: Mapping[str, Any], *, where: str, table_name: str,
                      exclude: Sequence[str] = ()) -> None:  # fmt: skip
    """Refuse keys that are no :class:`OllamaSource` keyword.

    Args:
        table: The keys to check.
        where: The scenario file, for the message.
        table_name: ``[feedback.ollama]`` or ``[feedback.agents.care]``.
        exclude: Keywords not allowed in that table (set elsewhere).

    Raises:
        ScenarioError: Naming the file, the table, the unknown keys and the allowed ones.

    """
    allowed = set(ollama_keywords()) - set(exclude)
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ScenarioError(
            f"{where}: {table_name} unknown key(s) {', '.join(unknown)}; expected some of "
            f"{', '.join(sorted(allowed))}"
        )


def _ollama_type(key: str, default: Any) -> tuple[type, ...] | None:
    if key == "options":
        return (dict,)
    if key == "keep_alive":
        return (str, int, float)
    if isinstance(default, bool):
        return (bool,)
    if isinstance(default, int):
        return (int,)
    if isinstance(default, float):
        return (int, float)
    if isinstance(default, str):
        return (str,)
    return None


def _plain_problem(value: Any, key: str) -> str | None:
    """Why ``value`` is not plain JSON-able TOML data (a datetime, say), or None."""
    if isinstance(value, datetime.date | datetime.time):
        return f"key {key} expects a string, number, boolean, array or table, found {value!r}"
    if isinstance(value, dict):
        for k, v in value.items():
            problem = _plain_problem(v, f"{key}.{k}")
            if problem:
                return problem
    elif isinstance(value, list):
        for i, v in enumerate(value):
            problem = _plain_problem(v, f"{key}[{i}]")
            if problem:
                return problem
    elif not isinstance(value, _PLAIN) and value is not None:
        return f"key {key} expects a string, number, boolean, array or table, found {value!r}"
    return None


def agent_keys(kind: str) -> dict[str, tuple[tuple[type, ...], str]]:
    """The keys a ``[feedback.agents.X]`` table of ``kind`` may hold (``source`` aside)."""
    keys = dict(AGENT_KEYS[kind])
    if kind == "ollama":
        for key, default in ollama_keywords().items():
            if key not in keys:
                types = _ollama_type(key, default)
                keys[key] = (types or (object,), "an OllamaSource option")
    return keys


def _agent_name(agent: Any) -> str:
    return agent if isinstance(agent, str) else str(agent.name)


def match_agents(names: Sequence[str], agents: Sequence[Any]) -> dict[str, str]:
    """Map panel agents to the ``[feedback.agents]`` table naming each.

    Names are compared ignoring case, ``_``, ``-`` and spaces (``social-justice`` is
    ``social_justice``); an agent given as a cluster object also matches a table named
    after one of its aliases (``deontologist``).

    Args:
        names: The table names.
        agents: The panel's agents: names, or cluster objects (``.name``, ``.names``).

    Returns:
        ``{agent name: table name}`` for every agent some table names.

    """
    by_norm = {_norm(n): n for n in names}
    out: dict[str, str] = {}
    for agent in agents:
        name = _agent_name(agent)
        candidates = (name,) if isinstance(agent, str) else (name, *getattr(agent, "names", ()))
        for candidate in candidates:
            if _norm(candidate) in by_norm:
                out[name] = by_norm[_norm(candidate)]
                break
    return out


def check_agent_tables(
    agents: Any,
    *,
    where: str,
    clusters: Sequence[str],
    default_source: str,
    default_model: str,
) -> None:
    """Check ``[feedback.agents]``: every table, key, type, range and agent name.

    Args:
        agents: ``{agent name: table}`` as read from TOML.
        where: The scenario file (or override), for messages.
        clusters: ``[feedback].clusters`` (the names tables may use, with ``moral_agent``).
        default_source: ``[feedback].source`` (an ``ollama`` table without ``model``
            takes ``[feedback].model`` only when this is ``"ollama"``).
        default_model: ``[feedback].model``.

    Raises:
        ScenarioError: Naming the file, the ``[feedback.agents.<name>]`` table, what was
            expected, what was found and the fix.

    """
    if not isinstance(agents, Mapping):
        raise ScenarioError(
            f"{where}: key [feedback].agents expects a table of [feedback.agents.<name>] "
            f"tables, found {_found(agents)}"
        )
    known = {_norm(c): c for c in (*clusters, MORAL_AGENT)}
    seen: dict[str, str] = {}
    kinds = ", ".join(AGENT_SOURCE_KINDS)
    for name, table in agents.items():
        head = f"{where}: [feedback.agents.{name}]"
        if not isinstance(table, Mapping):
            raise ScenarioError(
                f'{head} expects a table such as {{ source = "rules" }}, found '
                f"{_found(table)}; write it as a [feedback.agents.{name}] table"
            )
        key = _norm(str(name))
        if key not in known:
            raise ScenarioError(
                f"{head} names no agent of the panel: expected one of "
                f"{', '.join(clusters)} or {MORAL_AGENT} ([feedback].clusters), found "
                f"{name!r}; fix the table's name, or add the cluster to [feedback].clusters"
            )
        if key in seen:
            raise ScenarioError(
                f"{head} and [feedback.agents.{seen[key]}] name the same agent "
                f"{known[key]!r}; keep one of the two tables"
            )
        seen[key] = str(name)
        kind = table.get("source")
        if kind is None:
            raise ScenarioError(f"{head} has no key source; add source = one of {kinds}")
        if kind not in AGENT_SOURCE_KINDS:
            raise ScenarioError(
                f"{head} key source expects one of {kinds}, found {_found(kind)}; fix source "
                '(a plug-in agent is source = "entry-point" with name = "pkg.module:Class" '
                "or an installed amuled_ma.agents name)"
            )
        allowed = agent_keys(kind)
        for k, value in table.items():
            if k == "source":
                continue
            if k not in allowed:
                raise ScenarioError(
                    f"{head} unknown key {k!r} for source = {kind!r}; expected some of "
                    f"{', '.join(['source', *sorted(allowed)])}; fix or remove the key"
                )
            problem = _plain_problem(value, k)
            if problem:
                raise ScenarioError(f"{head} {problem}")
            types, what = allowed[k]
            if object not in types and (
                not isinstance(value, types) or (isinstance(value, bool) and bool not in types)
            ):
                names = " or ".join(_TYPE_NAMES[t] for t in types)
                raise ScenarioError(
                    f"{head} key {k} expects {names} ({what}), found {_found(value)}; fix the value"
                )
            if k in _RANGES and not isinstance(value, bool):
                low, high, low_open, why = _RANGES[k]
                if value < low or value > high or (low_open and value == low):
                    left = "(" if low_open else "["
                    raise ScenarioError(
                        f"{head} key {k} expects a number in {left}{low}, {high}] ({why}), "
                        f"found {value!r}"
                    )
            if k == "host" and value:
                from amuled_ma.beliefs.hosts import normalize_host

                normalize_host(value, where=f"{head} key host")
            if k == "hosts":
                from amuled_ma.beliefs.hosts import normalize_hosts

                normalize_hosts(value, where=f"{head} key hosts")
        if kind == "ollama" and table.get("host") and table.get("hosts"):
            raise ScenarioError(
                f"{head} sets both host and hosts; keep host for one server, or hosts = "
                "[...] for a pool (list that server there too)"
            )
        if kind in _REQUIRED:
            required, example = _REQUIRED[kind]
            given = table.get(required)
            if kind == "ollama" and not given and default_source == "ollama" and default_model:
                continue
            if not isinstance(given, str) or not given.strip():
                also = (
                    " and [feedback].source is not 'ollama' (so [feedback].model is not an "
                    "Ollama model)"
                    if kind == "ollama"
                    else ""
                )
                raise ScenarioError(
                    f"{head} (source = {kind!r}) has no {required}{also}; add {example}"
                )


# ------------------------------------------------------------------ scenario -> sources
@dataclass(frozen=True)
class SourceSpec:
    """What :func:`~amuled_ma.beliefs.sources.make_source` builds for some agents.

    Attributes:
        kind: The ``make_source`` kind.
        options: Its keyword arguments (plain data).
        label: How messages name it (``"[feedback.agents.care] (source 'ollama', model
            'llama3.1:8b')"``).

    """

    kind: str
    options: dict[str, Any]
    label: str

    @property
    def key(self) -> str:
        """Canonical JSON of kind and options: equal keys build one shared source."""
        return json.dumps([self.kind, self.options], sort_keys=True, default=str)


def default_spec(scenario: Any, ollama_options: Callable[[Any], dict[str, Any]]) -> SourceSpec:
    """The source of ``[feedback].source`` (what every agent without a table uses).

    Args:
        scenario: The :class:`~amuled_ma.scenario.Scenario`.
        ollama_options: Returns ``[feedback.ollama]`` checked.

    Raises:
        ScenarioError: The replayed recording is not found, or ``[feedback.ollama]``
            holds unknown keys.

    """
    fb = scenario.feedback
    options: dict[str, Any] = {}
    if fb.source == "replay":
        path = scenario.recording_path(required=True)
        # "zero" is applied to the fused reward (PanelFeedback.miss_zero); the source
        # answers a miss with a uniform belief, counted as replay_miss
        policy = "uniform" if fb.miss_policy == "zero" else fb.miss_policy
        options.update(paths=str(path), miss_policy=policy)
    elif fb.source == "ollama":
        options.update(
            model=fb.model,
            host=fb.host or None,
            hosts=list(fb.hosts) or None,
            concurrency=fb.concurrency,
            timeout_s=fb.timeout_s,
            **ollama_options(scenario),
        )
    elif fb.source == "rules":
        options.update(policy="human")
    return SourceSpec(fb.source, options, f"[feedback].source = {fb.source!r}")


def agent_spec(
    scenario: Any, name: str, table: Mapping[str, Any],
    ollama_options: Callable[[Any], dict[str, Any]],
) -> SourceSpec:  # fmt: skip
    """The source of one ``[feedback.agents.<name>]`` table, defaults filled in.

    Args:
        scenario: The scenario.
        name: The table's name.
        table: The table (already checked by :func:`check_agent_tables`).
        ollama_options: Returns ``[feedback.ollama]`` checked.

    Raises:
        ScenarioError: The agent's recording is not found.

    """
    fb = scenario.feedback
    kind = table["source"]
    head = f"[feedback.agents.{name}]"
    rest = {k: v for k, v in table.items() if k != "source"}
    options: dict[str, Any]
    detail = ""
    if kind == "replay":
        recording = rest.get("recording") or fb.recording
        try:
            path = (
                scenario.replace("feedback", recording=recording).recording_path(required=True)
                if "recording" in rest
                else scenario.recording_path(required=True)
            )
        except ScenarioError as error:
            text = str(error)
            if "recording" in rest:
                text = text.replace("[feedback].recording", f"{head} recording")
            raise ScenarioError(text) from None
        policy = "uniform" if fb.miss_policy == "zero" else fb.miss_policy
        options = {"paths": str(path), "miss_policy": policy}
        detail = f", recording {path.name!r}"
    elif kind == "ollama":
        own_host, own_hosts = rest.pop("host", None), rest.pop("hosts", None)
        if not own_host and not own_hosts:  # the table names no server: [feedback]'s
            own_host, own_hosts = fb.host, list(fb.hosts)
        options = {
            "model": rest.pop("model", None) or fb.model,
            "host": own_host or None,
            "hosts": list(own_hosts) if own_hosts else None,
            "concurrency": rest.pop("concurrency", fb.concurrency),
            "timeout_s": float(rest.pop("timeout_s", fb.timeout_s)),
        }
        options.update(ollama_options(scenario))
        options.update(rest)
        detail = f", model {options['model']!r}"
    elif kind == "rules":
        options = {"policy": rest.get("policy", "human")}
    elif kind == "terminal":
        options = {"person": rest.get("person", "human"), "attempts": rest.get("attempts", 3)}
    elif kind == "entry-point":
        options = {"name": rest["name"], "options": dict(rest.get("options", {}))}
        detail = f", name {rest['name']!r}"
    elif kind == "policy":
        options = {
            "path": str(scenario.resolve(rest["path"])),
            "key": rest.get("key", ""),
            "module": rest.get("module", ""),
            "kwargs": dict(rest.get("kwargs", {})),
            "activation": rest.get("activation", "tanh"),
        }
        detail = f", path {rest['path']!r}"
    else:  # pragma: no cover - check_agent_tables refuses other kinds
        raise ScenarioError(f"{head}: unknown source {kind!r}")
    return SourceSpec(kind, options, f"{head} (source {kind!r}{detail})")


def panel_specs(
    scenario: Any, agents: Sequence[str], ollama_options: Callable[[Any], dict[str, Any]]
) -> tuple[dict[str, SourceSpec], SourceSpec | None, list[tuple[BaseException, str]]]:
    """Each panel agent's source specification.

    Args:
        scenario: The scenario.
        agents: The panel's agents: names (cluster names, ``moral_agent``) or cluster
            objects (see :func:`match_agents`).
        ollama_options: Returns ``[feedback.ollama]`` checked.

    Returns:
        ``({agent name: spec}`` for agents with a table, the default spec, the problems
        ``[(error, label)]`` of specs that could not be made (a recording not found)``)``.
        The default is ``None`` when every agent has a table (``[feedback].source`` is
        then not built).

    """
    tables = dict(scenario.feedback.agents)
    matched = match_agents(list(tables), agents)
    names = [_agent_name(a) for a in agents]
    specs: dict[str, SourceSpec] = {}
    problems: list[tuple[BaseException, str]] = []
    for agent, table in matched.items():
        try:
            specs[agent] = agent_spec(scenario, table, tables[table], ollama_options)
        except AmuledError as error:
            kind = tables[table].get("source")
            problems.append((error, f"[feedback.agents.{table}] (source {kind!r})"))
    default = None
    others = [a for a in names if a not in matched]
    if others:
        try:
            default = default_spec(scenario, ollama_options)
            default = dataclasses.replace(
                default, label=f"{default.label} (agents {', '.join(others)})"
            )
        except AmuledError as error:
            label = f"[feedback].source = {scenario.feedback.source!r}"
            problems.append((error, f"{label} (agents {', '.join(others)})"))
    return specs, default, problems


def _without(error: BaseException, where: str) -> str:
    """The error's message without a leading ``"<where>: "`` (it is said once, first)."""
    text = str(error)
    return text[len(where) + 2 :] if text.startswith(f"{where}: ") else text


def build_members(
    specs: Mapping[str, SourceSpec],
    default: SourceSpec | None,
    *,
    where: str,
    build: Callable[..., BeliefSource],
    problems: Sequence[tuple[BaseException, str]] = (),
) -> tuple[dict[str, BeliefSource], BeliefSource | None]:
    """Build every distinct member source once and check it before anything is asked.

    The preflight, per distinct source: building it (a replay recording is read and
    checked, a policy file loaded, a plug-in resolved and built), then ``check()`` where
    the source has one (Ollama: the server answers and has the model), then, for a
    replay member, that its recording holds per-agent beliefs. Every problem is
    collected; none is asked a belief.

    Args:
        specs: ``{agent: spec}`` of the agents with their own table.
        default: The default source's spec (``None``: every agent has a table).
        where: The scenario file, for messages.
        build: ``make_source`` (``(kind, **options) -> BeliefSource``).
        problems: Problems found before (:func:`panel_specs`), reported with the others.

    Returns:
        ``({agent: source}, default source)``; agents with equal specs share one object,
        and so do an agent and the default when their specs are equal.

    Raises:
        AmuledError: One problem: the member's own error class, its message prefixed
            with the agent's table and source; several: a :class:`ScenarioError`
            listing each, one per line. Every source built is closed first.

    """
    distinct: dict[str, tuple[SourceSpec, list[str]]] = {}
    if default is not None:
        distinct[default.key] = (default, [])
    for agent, spec in specs.items():
        distinct.setdefault(spec.key, (spec, []))[1].append(agent)
    built: dict[str, BeliefSource] = {}
    problems = list(problems)
    for key, (spec, agents) in distinct.items():
        label = spec.label
        if spec is default and agents:
            tables = ", ".join(f"[feedback.agents.{a}]" for a in agents)
            label = f"{label}, also {tables}"
        elif len(agents) > 1:
            label = f"{label} (shared by agents {', '.join(agents)})"
        try:
            source = build(spec.kind, **json.loads(json.dumps(spec.options)))
        except Exception as error:
            problems.append((error, label))
            continue
        built[key] = source
        check = getattr(source, "check", None)
        try:
            if callable(check):
                check()
            recordings = getattr(source, "recordings", None) if spec.kind == "replay" else None
            fused_only = [r for r in recordings or () if getattr(r, "fused_only", False)]
            if fused_only:
                raise ScenarioError(
                    f"{fused_only[0].path} keeps only the authors' fused belief per state "
                    "('beliefs': null), so it cannot answer per agent; name a recording "
                    'with per-cluster beliefs (e.g. recording = "driving-llama-3_1-70b")'
                )
        except Exception as error:
            problems.append((error, label))
    if problems:
        for source in built.values():
            with contextlib.suppress(Exception):  # the preflight error matters more
                source.close()
        if len(problems) == 1:
            error, label = problems[0]
            text = f"{where}: {label}: {_without(error, where)}"
            wrapped: BaseException = ScenarioError(text)
            if isinstance(error, AmuledError):
                with contextlib.suppress(TypeError):  # an error class with another signature
                    wrapped = type(error)(text)
            raise wrapped from error
        lines = "\n".join(f"  - {label}: {_without(e, where)}" for e, label in problems)
        raise ScenarioError(
            f"{where}: {len(problems)} belief sources of the panel cannot be used; fix each "
            f"before training:\n{lines}"
        ) from problems[0][0]
    routes = {agent: built[spec.key] for agent, spec in specs.items()}
    return routes, built[default.key] if default is not None else None


def scenario_ollama_options(scenario: Any) -> dict[str, Any]:
    """``[feedback.ollama]`` of a scenario, checked against :class:`OllamaSource`'s keywords.

    Raises:
        ScenarioError: An unknown key, naming the file and the allowed keys.

    """
    check_ollama_keys(
        scenario.feedback.ollama,
        where=str(scenario.path or scenario.name),
        table_name="[feedback.ollama]",
        exclude=("model", "host", "hosts", "concurrency", "timeout_s"),
    )
    return dict(scenario.feedback.ollama)


def preflight(scenario: Any, agents: Sequence[Any]) -> None:
    """Build and check the source of every agent of a panel, then close them.

    The check :func:`amuled_ma.deliberation.feedback.make_source` runs, without a store: a
    planner can call it for every fine-tune before the first job trains.

    Args:
        scenario: The scenario.
        agents: The panel's agents (names or cluster objects).

    Raises:
        AmuledError: As :func:`build_members`.

    """
    from amuled_ma.beliefs.sources import make_source

    specs, default, problems = panel_specs(scenario, agents, scenario_ollama_options)
    routes, fallback = build_members(
        specs,
        default,
        where=str(scenario.path or scenario.name),
        build=make_source,
        problems=problems,
    )
    closed: set[int] = set()
    for source in [*routes.values(), *([fallback] if fallback is not None else [])]:
        if id(source) not in closed:
            closed.add(id(source))
            source.close()
