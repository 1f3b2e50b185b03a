"""``[feedback.agents.<name>]`` and cluster ``[source]`` tables as typed source specs."""

from __future__ import annotations

import typing
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.memory import leaves
from amuled_ma.scenario.paths import find_recording
from amuled_ma.scenario.ranges import RANGE_ERRORS, TOML_NAMES, field_range, found
from amuled_ma.servers.urls import normalize_host, normalize_hosts

if TYPE_CHECKING:
    from amuled_ma.scenario.sections import FeedbackConfig

#: Name of the unprompted moral agent (the ``moral`` variant; ``moral_agent`` in recordings).
MORAL_AGENT = "moral_agent"

_OPTION = "an OllamaSource option"


#: ``concurrency`` of ``[feedback]`` and of an ``ollama`` table.
Concurrency = Annotated[
    int, Field(ge=1, le=1024, description="LLM requests in flight, one connection each")
]
#: ``timeout_s`` of ``[feedback]`` and of an ``ollama`` table.
TimeoutS = Annotated[
    float,
    Field(gt=0, le=86_400, description="seconds per LLM request: 0 fails all, above a day hangs"),
]


def norm(name: str) -> str:
    """A name compared ignoring case, ``_``, ``-`` and spaces (``social-justice``)."""
    return "".join(ch for ch in name.lower() if ch.isalnum())


class _Spec(BaseModel):
    """Base of the agent source specs: strict, frozen, no unknown keys, no NaN."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    #: The key a table of this kind must hold, and an example for the fix (None: none).
    required: ClassVar[tuple[str, str] | None] = None

    def given(self) -> dict[str, Any]:
        """The keys the table set (besides ``source``), as plain data."""
        return self.model_dump(exclude_unset=True, exclude={"source"})

    def detail(self, options: Mapping[str, Any]) -> str:
        """What names this member in messages, after its kind (``, model 'x'``)."""
        return ""

    def source_options(
        self, feedback: FeedbackConfig, resolve: Callable[[str], Path], where: str, head: str
    ) -> dict[str, Any]:
        """The keyword arguments of this kind's source, ``[feedback]``'s values inherited.

        ``where`` (the scenario) and ``head`` (the table) name it in messages.

        Raises:
            ScenarioError: A file the table names is not found.
        """
        return self.model_dump(exclude={"source"})


class ReplaySpec(_Spec):
    """``source = "replay"``: a recording of the authors' (or our) beliefs."""

    source: Literal["replay"]
    recording: str = Field(
        "", description="a recording file or name (default [feedback].recording)"
    )

    def source_options(  # noqa: D102 - see _Spec
        self, feedback: FeedbackConfig, resolve: Callable[[str], Path], where: str, head: str
    ) -> dict[str, Any]:
        key = f"{head} recording" if self.recording else "[feedback].recording"
        path = find_recording(
            self.recording or feedback.recording, resolve, where=where, required=True, key=key
        )
        # "zero" is applied to the fused reward (the panel feedback's miss_zero); the
        # source answers a miss with a uniform belief, counted as replay_miss
        policy = "uniform" if feedback.miss_policy == "zero" else feedback.miss_policy
        return {"paths": str(path), "miss_policy": policy}

    def detail(self, options: Mapping[str, Any]) -> str:  # noqa: D102 - see _Spec
        return f", recording {Path(options['paths']).name!r}"


class OllamaSpec(_Spec):
    """``source = "ollama"``: an LLM on an Ollama server.

    A key left out takes ``[feedback]``'s value, then the source's default; only keys a table
    sets are passed on.
    """

    required = ("model", 'model = "llama3.1:8b" (an Ollama model name)')

    source: Literal["ollama"]
    model: str = Field("", description="an Ollama model name")
    host: str = Field("", description="the Ollama server URL")
    hosts: list[str] = Field(
        default_factory=list, description="a pool of Ollama server URLs (instead of host)"
    )
    concurrency: Concurrency = 2
    timeout_s: TimeoutS = 120.0
    structured: bool = Field(True, description=_OPTION)
    reasoning: bool = Field(True, description=_OPTION)
    reasoning_max_chars: int = Field(400, description=_OPTION)
    temperature: float = Field(0.0, description=_OPTION)
    seed: int = Field(42, description=_OPTION)
    num_ctx: int = Field(8192, description=_OPTION)
    num_predict: int = Field(1024, description=_OPTION)
    options: dict[str, Any] = Field(default_factory=dict, description=_OPTION)
    retries: int = Field(2, description=_OPTION)
    retry_timeouts: bool = Field(False, description=_OPTION)
    backoff_s: float = Field(0.5, description=_OPTION)
    backoff_max_s: float = Field(8.0, description=_OPTION)
    parse_retries: int = Field(1, description=_OPTION)
    keep_alive: str | int | float | None = Field(None, description=_OPTION)
    check_timeout_s: float = Field(4.5, description=_OPTION)
    down_for_s: float = Field(5.0, description=_OPTION)

    def source_options(  # noqa: D102 - see _Spec
        self, feedback: FeedbackConfig, resolve: Callable[[str], Path], where: str, head: str
    ) -> dict[str, Any]:
        rest = self.given()
        own_host, own_hosts = rest.pop("host", None), rest.pop("hosts", None)
        if not own_host and not own_hosts:  # the table names no server: [feedback]'s
            own_host, own_hosts = feedback.host, list(feedback.hosts)
        options = {
            "model": rest.pop("model", None) or feedback.model,
            "host": own_host or None,
            "hosts": list(own_hosts) if own_hosts else None,
            "concurrency": rest.pop("concurrency", feedback.concurrency),
            "timeout_s": float(rest.pop("timeout_s", feedback.timeout_s)),
        }
        return {**options, **feedback.ollama, **rest}

    def detail(self, options: Mapping[str, Any]) -> str:  # noqa: D102 - see _Spec
        return f", model {options['model']!r}"


class RulesSpec(_Spec):
    """``source = "rules"``: the synthetic human, ``judge:<value>``, or ``module:function``."""

    source: Literal["rules"]
    policy: str = Field(
        "human",
        description="'human', 'judge:<value>' (the task's own judge), or "
        "'pkg.module:function' allowed with --allow-plugin",
    )


class TerminalSpec(_Spec):
    """``source = "terminal"``: a person typing beliefs at the terminal."""

    source: Literal["terminal"]
    person: str = Field("human", description="who answers (kept apart in the store)")
    attempts: int = Field(3, ge=1, le=100, description="answer lines read per state")


class EntryPointSpec(_Spec):
    """``source = "entry-point"``: a plug-in agent (installed name or ``module:Class``).

    A ``module:Class`` is imported only with ``--allow-plugin module:Class``; an installed
    ``amuled_ma.agents`` entry point needs no flag.
    """

    required = (
        "name",
        'name = "my_pkg.agents:MyAgent" (or an installed amuled_ma.agents name)',
    )

    source: Literal["entry-point"]
    name: str = Field(
        description="an installed amuled_ma.agents name, or 'pkg.module:Class' allowed with "
        "--allow-plugin"
    )
    options: dict[str, Any] = Field(
        default_factory=dict, description="the plug-in's keyword arguments"
    )

    def detail(self, options: Mapping[str, Any]) -> str:  # noqa: D102 - see _Spec
        return f", name {self.name!r}"


class PolicySpec(_Spec):
    """``source = "policy"``: a saved torch policy's action distribution."""

    required = (
        "path",
        'path = "policies/virtue.pt" (a torch.save state dict, relative to the scenario file)',
    )

    source: Literal["policy"]
    path: str = Field(description="a torch.save state dict, relative to the scenario file")
    key: str = Field("", description="the state dict's key in a checkpoint dict")
    module: str = Field(
        "", description="'pkg.module:Class' of the network, allowed with --allow-plugin"
    )
    kwargs: dict[str, Any] = Field(default_factory=dict, description="keyword arguments of module")
    activation: str = Field("tanh", description="activation of an inferred MLP")

    def detail(self, options: Mapping[str, Any]) -> str:  # noqa: D102 - see _Spec
        return f", path {self.path!r}"

    def source_options(  # noqa: D102 - see _Spec
        self, feedback: FeedbackConfig, resolve: Callable[[str], Path], where: str, head: str
    ) -> dict[str, Any]:
        return {**self.model_dump(exclude={"source"}), "path": str(resolve(self.path))}


#: An agent table: one of the spec models, chosen by its ``source``.
AgentSpec = Annotated[
    ReplaySpec | OllamaSpec | RulesSpec | TerminalSpec | EntryPointSpec | PolicySpec,
    Field(discriminator="source"),
]
#: The one registry of the source kinds an agent table may name: kind -> spec model.
AGENT_SPECS: dict[str, type[_Spec]] = {
    typing.get_args(spec.model_fields["source"].annotation)[0]: spec
    for spec in typing.get_args(typing.get_args(AgentSpec)[0])
}
#: Source kinds a ``[feedback.agents.<name>]`` table may name, in the order of messages.
AGENT_SOURCE_KINDS = tuple(AGENT_SPECS)


def _types(annotation: Any) -> tuple[type, ...]:
    """The plain Python types a key of ``annotation`` accepts (int also for float)."""
    origin = typing.get_origin(annotation)
    if origin is list:
        return (list,)
    if origin is dict:
        return (dict,)
    args = typing.get_args(annotation)
    if args and origin is not Literal:
        return tuple(t for a in args if a is not type(None) for t in _types(a))
    if annotation is float:
        return (int, float)
    return (annotation,)


def _agent_problem(model: type[_Spec], table: Mapping[str, Any], error: ValidationError) -> str:
    """The first problem pydantic found in an agent table, as the agent table messages say it."""
    first = error.errors(include_url=False)[0]
    key = str(first["loc"][0])
    kind = table["source"]
    if first["type"] == "extra_forbidden":
        keys = ", ".join(["source", *sorted(k for k in model.model_fields if k != "source")])
        return (
            f"unknown key {key!r} for source = {kind!r}; expected some of {keys}; fix or "
            "remove the key"
        )
    value = table.get(key)
    info = model.model_fields[key]
    rng = field_range(model, key)
    if first["type"] in RANGE_ERRORS and rng is not None:
        left = "(" if rng.low_open else "["
        return (
            f"key {key} expects a number in {left}{rng.low}, {rng.high}] ({rng.why}), "
            f"found {value!r}"
        )
    names = " or ".join(TOML_NAMES[t] for t in _types(info.annotation))
    return (
        f"key {key} expects {names} ({info.description or ''}), found {found(value)}; fix the value"
    )


def check_agent_table(
    head: str, table: object, *, default_source: str = "", default_model: str = ""
) -> BaseModel:
    """Validate one agent table into its spec (``head`` starts every message).

    An ``ollama`` table without ``model`` takes ``default_model`` if ``default_source`` is ollama.

    Raises:
        ScenarioError: Naming the table, what was expected, what was found and the fix.
    """
    kinds = ", ".join(AGENT_SOURCE_KINDS)
    if isinstance(table, BaseModel):
        return table
    if not isinstance(table, Mapping):
        raise ScenarioError(
            f'{head} expects a table such as {{ source = "rules" }}, found {found(table)}'
        )
    kind = table.get("source")
    if kind is None:
        raise ScenarioError(f"{head} has no key source; add source = one of {kinds}")
    if kind not in AGENT_SPECS:
        raise ScenarioError(
            f"{head} key source expects one of {kinds}, found {found(kind)}; fix source "
            '(a plug-in agent is source = "entry-point" with name = an installed '
            'amuled_ma.agents name, or "pkg.module:Class" and --allow-plugin pkg.module:Class)'
        )
    model = AGENT_SPECS[kind]
    for name, given in table.items():  # pydantic takes a date inside a free-form table
        for key, value in leaves(str(name), given):
            if value is not None and not isinstance(value, str | int | float | bool):
                raise ScenarioError(
                    f"{head} key {key} expects a string, number, boolean, array or table, "
                    f"found {value!r}"
                )
    host, hosts = table.get("host"), table.get("hosts")
    if kind == "ollama" and isinstance(host, str) and host:
        normalize_host(host, where=f"{head} key host")
    if kind == "ollama" and isinstance(hosts, list):
        normalize_hosts(hosts, where=f"{head} key hosts")
    if kind == "ollama" and host and hosts:
        raise ScenarioError(
            f"{head} sets both host and hosts; keep host for one server, or hosts = "
            "[...] for a pool (list that server there too)"
        )
    if model.required is not None:
        required, example = model.required
        given = table.get(required)
        inherits = kind == "ollama" and default_source == "ollama" and bool(default_model)
        if not (inherits and not given) and (not isinstance(given, str) or not given.strip()):
            also = (
                " and [feedback].source is not 'ollama' (so [feedback].model is not an "
                "Ollama model)"
                if kind == "ollama"
                else ""
            )
            raise ScenarioError(
                f"{head} (source = {kind!r}) has no {required}{also}; add {example}"
            )
    try:
        return model.model_validate(table)
    except ValidationError as error:
        raise ScenarioError(f"{head} {_agent_problem(model, table, error)}") from None


def check_agent_tables(
    agents: object,
    *,
    where: str,
    clusters: Sequence[str],
    default_source: str,
    default_model: str,
) -> dict[str, BaseModel]:
    """Validate ``[feedback.agents]`` into ``{name: spec}``, checking every agent name."""
    if not isinstance(agents, Mapping):
        raise ScenarioError(
            f"{where}: key [feedback].agents expects a table of [feedback.agents.<name>] "
            f"tables, found {found(agents)}"
        )
    known = {norm(c): c for c in (*clusters, MORAL_AGENT)}
    seen: dict[str, str] = {}
    specs: dict[str, BaseModel] = {}
    for name, table in agents.items():
        head = f"{where}: [feedback.agents.{name}]"
        if not isinstance(table, Mapping | BaseModel):
            raise ScenarioError(
                f'{head} expects a table such as {{ source = "rules" }}, found '
                f"{found(table)}; write it as a [feedback.agents.{name}] table"
            )
        key = norm(str(name))
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
        specs[name] = check_agent_table(
            head, table, default_source=default_source, default_model=default_model
        )
    return specs


def match_agents(names: Sequence[str], agents: Sequence[Any]) -> dict[str, str]:
    """``{agent name: table name}`` for every panel agent some ``[feedback.agents]`` table names.

    Names compare by `norm`; a cluster object also matches a table named after an alias.
    """
    by_norm = {norm(n): n for n in names}
    out: dict[str, str] = {}
    for agent in agents:
        name = agent if isinstance(agent, str) else str(agent.name)
        candidates = (name,) if isinstance(agent, str) else (name, *getattr(agent, "names", ()))
        for candidate in candidates:
            if norm(candidate) in by_norm:
                out[name] = by_norm[norm(candidate)]
                break
    return out
