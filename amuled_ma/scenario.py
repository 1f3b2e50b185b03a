"""Scenarios: everything one experiment needs, read from a TOML file and validated.

A scenario file has one table per concern (``[task]``, ``[ppo]``, ``[base]``,
``[finetune]``, ``[feedback]``, ``[evaluation]``, ``[output]``); each maps onto a frozen
pydantic v2 model below (:class:`TaskConfig`, :class:`PPOConfig`, ...), and the whole file
onto :class:`Scenario`. Keys left out take the defaults below, which follow the paper
(Dubey, Dailisan, Mahajan, "AMULED") and CleanRL's PPO.

pydantic validates every key, on load (:func:`load_scenario`, :func:`scenario_from_dict`),
on ``--set`` overrides (:meth:`Scenario.replace`) and on construction in code: types are
strict (an integer is never read from ``1e8`` or ``true``; a float key takes an integer),
unknown keys are refused (``extra="forbid"``), choices are ``Literal`` types and every
number has a range declared on its field (``Field(ge=..., gt=..., le=..., lt=...)``, the
reason as its ``description``; :func:`field_range` reads it back). NaN and infinities are
always refused, also inside the free tables ``[task].options``, ``[feedback].ollama`` and
``[feedback.agents]``; so are sizes whose buffers would not fit in
:data:`MEMORY_FRACTION` of the machine's memory and runs longer than
:data:`MAX_ENV_STEPS` (model validators, across keys). Values used as folder names (the
scenario ``name``, ``[task].name``) must be one safe path component
(:func:`check_path_component`); :func:`safe_child` builds a path below a root and refuses
one that would leave it.

Any failure is one :class:`~amuled_ma.errors.ScenarioError` line naming the file, the
``[section].key``, what was expected (and why, for a range) and what was found, converted
from pydantic's :class:`~pydantic.ValidationError` by :func:`scenario_error`.

Relative paths in a scenario (recordings, belief store, output folder) are resolved
against the scenario file's folder, never the current directory. A shipped scenario
can be named without a path (``amuled run findmilk``): see :func:`resolve_scenario_path`.
"""

from __future__ import annotations

import difflib
import itertools
import math
import os
import tomllib
import typing
from collections.abc import Callable, Mapping
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from amuled_ma.errors import ScenarioError
from amuled_ma.resources import read_text, scenarios_dir

#: The five moral clusters of the paper (Table 1), in the recordings' order.
PAPER_CLUSTERS = ("consequentialist", "deontological", "virtue", "care", "social_justice")

#: Most environment steps one training run may take: ``[base].total_steps``, and
#: ``iterations x num_envs x num_steps_per_env`` of ``[finetune]``. 20,000x the paper's
#: 500,000 and about 28 hours at 100,000 steps/s: a larger value is a typo, not a run.
MAX_ENV_STEPS = 10**10

#: Share of the machine's physical memory the estimated buffers of one section may fill.
MEMORY_FRACTION = 0.5

#: Estimated bytes of one stored rollout transition: the observation (up to
#: :data:`ASSUMED_OBS_DIM` floats), PPO's per-step buffers (action, reward, done, value,
#: log-probability, return, advantage, the action distribution), the fused beliefs of
#: fine-tuning and a mini-batch's forward and backward activations, times a safety factor.
BYTES_PER_TRANSITION = 4096

#: Estimated bytes of one evaluation episode (a task copy's state, its slice of the
#: batched forward pass and its Python metrics record), with a safety factor.
BYTES_PER_EPISODE = 16_384

#: Bytes of one network parameter: float32 x (weight, gradient, Adam's two moments) x
#: two networks (actor and critic).
BYTES_PER_PARAMETER = 32

#: Observation length and action count the memory estimates assume: generous upper
#: bounds of the tasks (FindMilk: 8 observations, 4 actions; Driving: 11 and 3), so the
#: check needs no task import.
ASSUMED_OBS_DIM = 64
ASSUMED_NUM_ACTIONS = 16

#: Machine memory assumed where ``os.sysconf`` cannot tell (8 GiB).
FALLBACK_MEMORY_BYTES = 8 * 2**30

#: Largest seed: every RNG used (torch, the tasks' int64 streams) takes a 64-bit seed.
MAX_SEED = 2**63 - 1

#: Longest name accepted as a path component.
MAX_NAME_LENGTH = 100

#: What :func:`check_path_component` allows, quoted in its errors.
NAME_RULE = (
    f"1 to {MAX_NAME_LENGTH} characters; no '/', '\\', ':' or '..'; no control "
    "characters; not starting with '.' or '-'; no leading or trailing space"
)

#: The source named in errors of a scenario or section built in code (no file).
BUILT_IN_CODE = "<scenario built in code>"

#: ``[feedback].source``: the belief source of agents without a ``[feedback.agents]`` table.
FeedbackSource = Literal["replay", "ollama", "rules"]
#: ``[feedback].miss_policy``: what a replay miss gives.
MissPolicy = Literal["uniform", "fallback", "error", "zero"]
#: ``[finetune].recipe``: how the KL anchor enters the fine-tuning reward.
Recipe = Literal["equation", "authors"]
#: ``[ppo].activation``: rsl-rl's names of the hidden activation.
Activation = Literal["tanh", "relu", "elu", "selu", "lrelu", "sigmoid", "identity"]
#: ``[evaluation].modes``: action selection of the evaluation episodes.
EvaluationMode = Literal["greedy", "sampled"]
#: ``[feedback.distill].model``: the distilled reward model's kind.
DistillModel = Literal["mlp"]
#: ``[feedback.distill].selection``: which new states the budget spends on.
DistillSelection = Literal["uncertainty", "random"]


@dataclass(frozen=True)
class Range:
    """The allowed values of a numeric scenario key; NaN and infinities never are.

    A section model declares its ranges as pydantic ``Field`` bounds; :func:`field_range`
    and :func:`field_length` read them back as a ``Range``, which describes them in
    errors and in ``docs/learning.md``.

    Attributes:
        low: Smallest allowed value (None: no lower end).
        high: Largest allowed value (None: no upper end).
        low_open: Exclude ``low`` itself.
        high_open: Exclude ``high`` itself.
        why: The reason for the range, quoted in errors and docs.

    """

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    why: str = ""

    def __contains__(self, value: object) -> bool:
        """Whether ``value`` is a finite real number inside the range."""
        if isinstance(value, bool) or not isinstance(value, int | float):
            return False
        if not math.isfinite(value):
            return False
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            return False
        return not (
            self.high is not None and (value > self.high or (self.high_open and value == self.high))
        )

    def describe(self) -> str:
        """The range in words: ``in (0, 1]``, ``>= 1``, ``> 0``."""
        if self.low is not None and self.high is not None:
            left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
            return f"in {left}{_number(self.low)}, {_number(self.high)}{right}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {_number(self.low)}"
        if self.high is not None:
            return f"{'<' if self.high_open else '<='} {_number(self.high)}"
        return "(any finite value)"


def _number(value: float) -> str:
    if isinstance(value, int) and abs(value) >= 10_000:
        return f"{value:,}"
    return f"{value:g}" if isinstance(value, float) else str(value)


# Reasons of ranges shared by several keys (each key's ``Field(description=...)``).
_SEED_WHY = "a seed of torch and of the tasks' 64-bit random streams"
_EPOCHS_WHY = "optimisation passes over each rollout; CleanRL 4, authors 16"
_LR_WHY = "Adam step size: 0 learns nothing, beyond 1 the update diverges"
_SAVE_WHY = "iterations between checkpoints; 0 would divide by zero"
_ENVS_WHY = "parallel copies; with num_steps_per_env also checked against memory"
_STEPS_WHY = "rollout length per copy; with num_envs also checked against memory"
_WEIGHT_WHY = "a weight; negative flips the term's sign"


#: The validation context (``{"source": <file or override>}``) of the scenario being
#: validated. pydantic passes ``model_validate``'s context to validators but calls a model's
#: own ``__init__`` (the section models have one) without it, so :func:`_validate` also
#: sets it here for :func:`_init` to pass on (the pattern of pydantic's documentation,
#: "Using validation context with BaseModel initialization").
_CONTEXT: ContextVar[dict[str, str] | None] = ContextVar("amuled_scenario_context", default=None)


def _init(model: BaseModel, data: dict[str, Any], loc: tuple[str, ...]) -> None:
    """Validate ``data`` into ``model``, the ``__init__`` of the scenario models.

    Inside the validation of a file (:func:`_validate`) pydantic's error is left to it, to
    be reported with the file's name; built in code, it is converted here.
    """
    context = _CONTEXT.get()
    try:
        model.__pydantic_validator__.validate_python(data, self_instance=model, context=context)
    except ValidationError as error:
        if context is not None:
            raise
        raise scenario_error(error, BUILT_IN_CODE, loc) from None


def _source(info: ValidationInfo) -> str:
    """The file (or override) being validated: the validation context's ``source``."""
    context = info.context
    if isinstance(context, Mapping) and isinstance(context.get("source"), str):
        return context["source"]
    return BUILT_IN_CODE


class _Section(BaseModel):
    """Base of the section models: strict, frozen, no unknown keys, no NaN.

    Built in code (``TaskConfig(seed=-1)``), a section is validated like a file and a
    failure raises :class:`~amuled_ma.errors.ScenarioError`, not pydantic's error.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    #: The table's name in a scenario file (``task`` for ``[task]``).
    section: ClassVar[str] = ""

    def __init__(self, /, **data: Any) -> None:
        _init(self, data, (self.section,))


def _finite_table(section: str, value: Any, info: ValidationInfo) -> Any:
    """Refuse NaN and infinities anywhere in a free-form table, naming the nested key."""
    _check_finite(f"[{section}].{info.field_name}", value, _source(info))
    return value


class TaskConfig(_Section):
    """The task environment.

    Attributes:
        name: Task name known to :func:`amuled_ma.tasks.get_task` (``findmilk``, ``driving``);
            also a file name (prompt templates), so one safe path component.
        seed: Base random seed of the run.
        max_steps: Episode step limit; 0 keeps the task's own default.
        options: Extra keyword options passed to the task constructor.

    """

    section: ClassVar[str] = "task"

    name: str = "findmilk"
    seed: int = Field(1, ge=0, le=MAX_SEED, description=_SEED_WHY)
    max_steps: int = Field(
        0, ge=0, le=10**7, description="episode step limit; 0 keeps the task's default"
    )
    options: dict[str, Any] = Field(default_factory=dict)

    @field_validator("name")
    @classmethod
    def _name_is_a_folder_name(cls, value: str, info: ValidationInfo) -> str:
        return check_path_component(value, f"{_source(info)}: key [task].name")

    @field_validator("options")
    @classmethod
    def _options_are_finite(cls, value: Any, info: ValidationInfo) -> Any:
        return _finite_table("task", value, info)


class PPOConfig(_Section):
    """PPO hyperparameters shared by base training and fine-tuning (CleanRL ``ppo.py`` defaults).

    Attributes:
        hidden_dims: Hidden layer widths of the actor and the critic MLPs.
        activation: Hidden activation (rsl-rl name).
        learning_rate: Adam learning rate.
        anneal_lr: Linearly anneal the learning rate to 0 over the run.
        gamma: Discount factor.
        lam: GAE lambda.
        clip_param: PPO clipping coefficient.
        entropy_coef: Entropy bonus coefficient.
        value_loss_coef: Value loss coefficient.
        max_grad_norm: Gradient clipping norm.
        num_learning_epochs: Optimisation epochs per iteration.
        num_mini_batches: Mini-batches per epoch.
        normalize_advantage_per_mini_batch: Normalise advantages per mini-batch (CleanRL)
            rather than per rollout.

    """

    section: ClassVar[str] = "ppo"

    hidden_dims: list[
        Annotated[
            int,
            Field(
                ge=1,
                le=65_536,
                description="units of a hidden layer; the networks are also checked against memory",
            ),
        ]
    ] = Field(
        default_factory=lambda: [64, 64],
        min_length=1,
        max_length=64,
        description="hidden layers; rsl-rl's MLP needs at least one",
    )
    activation: Activation = "tanh"
    learning_rate: float = Field(2.5e-4, gt=0, le=1, description=_LR_WHY)
    anneal_lr: bool = True
    gamma: float = Field(
        0.99, ge=0, le=1, description="discount factor: above 1 returns grow without bound"
    )
    lam: float = Field(
        0.95, ge=0, le=1, description="GAE lambda, a weight between TD(0) and Monte Carlo"
    )
    clip_param: float = Field(
        0.2,
        gt=0,
        lt=1,
        description="PPO ratio clip: the ratio is clipped to [1 - clip, 1 + clip], which must "
        "be positive",
    )
    entropy_coef: float = Field(0.01, ge=0, description=_WEIGHT_WHY)
    value_loss_coef: float = Field(0.5, ge=0, description=_WEIGHT_WHY)
    max_grad_norm: float = Field(
        0.5, gt=0, description="gradient norm clip: 0 would zero every update"
    )
    num_learning_epochs: int = Field(4, ge=1, le=1000, description=_EPOCHS_WHY)
    num_mini_batches: int = Field(
        4, ge=1, le=65_536, description="mini-batches per epoch; each needs transitions"
    )
    normalize_advantage_per_mini_batch: bool = True

    @model_validator(mode="after")
    def _networks_fit_in_memory(self, info: ValidationInfo) -> PPOConfig:
        _check_budget("ppo", dict(self), _source(info))
        return self


class BaseConfig(_Section):
    """Base training (paper, Simulation Studies): ``r = r_env + c * r_shaping``.

    Attributes:
        total_steps: Environment steps of the whole run (all copies together).
        num_envs: Parallel environment copies.
        num_steps_per_env: Rollout length per copy and iteration.
        shaping_coef: ``c`` of the ``shaped`` variant (the ``base`` variant uses 0).
        save_interval: Iterations between checkpoints.

    """

    section: ClassVar[str] = "base"

    total_steps: int = Field(
        500_000,
        ge=1,
        le=MAX_ENV_STEPS,
        description="env steps of the run, capped at MAX_ENV_STEPS (about 28 h at 100k steps/s)",
    )
    num_envs: int = Field(4, ge=1, description=_ENVS_WHY)
    num_steps_per_env: int = Field(128, ge=1, description=_STEPS_WHY)
    shaping_coef: float = Field(
        1.0, ge=0, description="weight c of the shaping reward (the tasks need c >= 0)"
    )
    save_interval: int = Field(100, ge=1, description=_SAVE_WHY)

    @model_validator(mode="after")
    def _rollouts_fit_in_memory(self, info: ValidationInfo) -> BaseConfig:
        _check_budget("base", dict(self), _source(info))
        return self


class FinetuneConfig(_Section):
    """Fine-tuning on fused feedback: ``r = -lambda_kl * KL(pi || pi_base) + f(B)[a]``.

    Attributes:
        lambda_kl: Weight of the per-sample KL anchor to the base policy.
        iterations: PPO iterations.
        num_envs: Parallel environment copies.
        num_steps_per_env: Rollout length per copy and iteration.
        num_learning_epochs: Optimisation epochs per iteration (overrides ``[ppo]``).
        learning_rate: Adam learning rate (overrides ``[ppo]``).
        anneal_lr: Anneal the learning rate (overrides ``[ppo]``).
        reinit_critic: Re-initialise the critic before fine-tuning.
        env_reward_coef: Weight of the task reward kept in the fine-tuning reward (paper: 0).
        save_interval: Iterations between checkpoints.
        recipe: How the KL anchor enters the reward: ``"equation"`` (the paper's equation,
            the per-sample ``log pi(a|s) - log pi_base(a|s)``) or ``"authors"`` (what the
            authors' scripts compute: the KL between the log-softmax over time of the
            taken actions' log-probabilities since the episode, or the iteration, began;
            see :mod:`amuled_ma.learn.anchors`).

    """

    section: ClassVar[str] = "finetune"

    lambda_kl: float = Field(
        2.5,
        ge=0,
        description="weight of the KL anchor to the base policy; negative rewards drifting away",
    )
    iterations: int = Field(
        1000,
        ge=1,
        le=10**8,
        description="PPO iterations; iterations x num_envs x num_steps_per_env is also capped",
    )
    num_envs: int = Field(1, ge=1, description=_ENVS_WHY)
    num_steps_per_env: int = Field(128, ge=1, description=_STEPS_WHY)
    num_learning_epochs: int = Field(16, ge=1, le=1000, description=_EPOCHS_WHY)
    learning_rate: float = Field(2.5e-4, gt=0, le=1, description=_LR_WHY)
    anneal_lr: bool = False
    reinit_critic: bool = True
    env_reward_coef: float = Field(0.0, ge=0, description=_WEIGHT_WHY)
    save_interval: int = Field(100, ge=1, description=_SAVE_WHY)
    recipe: Recipe = "equation"

    @model_validator(mode="after")
    def _rollouts_fit_and_run_is_capped(self, info: ValidationInfo) -> FinetuneConfig:
        _check_budget("finetune", dict(self), _source(info))
        return self


class DistillConfig(_Section):
    """``[feedback.distill]``: LLM feedback on a budget (``docs/distill.md``).

    A small ensemble of networks learns each panel member's belief from the states the
    panel was asked; during fine-tuning a new state is asked (panel and belief store, as
    without this table) or answered by the model, and the panel is asked about at most
    ``budget`` of the distinct states visited.

    Attributes:
        enabled: Distil at all (off: the panel answers every state).
        budget: A float in ``(0, 1]``: at most that share of the distinct states the
            fine-tune visits is asked (``max(1, floor(budget x visited))`` at any time);
            an integer ``>= 1``: at most that many distinct states. ``1.0`` is every
            state, ``1`` is one state.
        model: The model's kind: ``"mlp"`` (an ensemble of two-hidden-layer MLPs on the
            observation, one softmax head per member).
        ensemble: Networks in the ensemble (their disagreement is the uncertainty).
        hidden: Units of each hidden layer.
        selection: ``"uncertainty"`` (ask where the ensemble disagrees most or the state
            is far from every asked one) or ``"random"`` (the baseline).
        refit_every: Newly answered asked states between two refits (the first fits come
            after 1, 2, 4, ... states).
        holdout: Share of asked states kept out of the fit to measure the model's
            agreement with the panel.
        answer_misses: Answer an asked state's replay misses and abstentions by the model
            (status ``distilled_miss``, counted apart).
        seed: Seed of the fits and the random selection; unset: the job's training seed.

    """

    section: ClassVar[str] = "feedback.distill"

    enabled: bool = False
    budget: float | int = 0.1
    model: DistillModel = "mlp"
    ensemble: int = Field(
        5,
        ge=1,
        le=64,
        description="networks in the ensemble; their disagreement is the "
        "uncertainty (1: the novelty term alone)",
    )
    hidden: int = Field(
        64, ge=1, le=4096, description="units of each of the model's two hidden layers"
    )
    selection: DistillSelection = "uncertainty"
    refit_every: int = Field(
        32,
        ge=1,
        le=1_000_000,
        description="newly answered asked states between two refits of the model",
    )
    holdout: float = Field(
        0.2,
        ge=0,
        le=0.5,
        description="share of asked states kept out of the fit to measure agreement; above "
        "0.5 the model would learn from fewer states than it is judged on",
    )
    answer_misses: bool = False
    seed: int | None = Field(None, ge=0, le=MAX_SEED, description=_SEED_WHY)

    def __init__(self, /, **data: Any) -> None:
        _init(self, data, ("feedback", "distill"))

    @field_validator("budget", mode="before")
    @classmethod
    def _budget_is_a_share_or_a_count(cls, value: Any, info: ValidationInfo) -> Any:
        ok = not isinstance(value, bool) and (
            (isinstance(value, int) and value >= 1)
            or (isinstance(value, float) and math.isfinite(value) and 0 < value <= 1)
        )
        if not ok:
            raise ScenarioError(
                f"{_source(info)}: key [feedback.distill].budget expects a share in (0, 1] "
                "written as a float (0.1: at most 10% of the distinct states visited are "
                "asked) or a count >= 1 written as an integer (at most that many distinct "
                f"states), found {_found_name(value)} ({value!r})"
            )
        return value


class FeedbackConfig(_Section):
    """Where beliefs come from and how they are fused.

    Attributes:
        source: Belief source kind: ``replay``, ``ollama`` or ``rules``.
        recording: Recording file replayed by the ``replay`` source.
        model: LLM name for the ``ollama`` source.
        host: Ollama server URL; empty: ``$OLLAMA_HOST``, else ``http://127.0.0.1:11434``.
            Checked on load by :func:`amuled_ma.beliefs.hosts.normalize_host`.
        hosts: A pool of Ollama server URLs instead of ``host`` (each request goes to the
            least-busy live one, a dead one is left out and its requests retried on
            another; ``docs/ollama.md``, "A pool of servers"). Checked on load by
            :func:`amuled_ma.beliefs.hosts.normalize_hosts`; not with ``host``.
        concurrency: Requests in flight at once.
        timeout_s: Seconds before one request is abandoned.
        miss_policy: What a replay miss gives: ``uniform``, ``fallback``, ``error``, or
            ``zero`` (reward 0 for a state missing from the recording, as the authors'
            scripts did; counted as a miss).
        cluster_recording: The recording the ``clusters`` and ``aggregation`` ablations
            replay when ``recording`` keeps only fused beliefs (the paper's Driving
            gpt-4o-mini cache); empty: ``recording``.
        store: SQLite belief store (cache of every answer).
        clusters: Moral clusters of the panel.
        fusion: Fusion rule of the ``amuled`` variant, a name of
            :data:`amuled_ma.fusion.RULES` (``bjs-dst``, ``mean``, ``single:2``, ...). A
            plain string, not a ``Literal``: rules can be registered at run time
            (:func:`amuled_ma.fusion.register_rule`) and take a parameter after ``:``.
        ollama: Further keyword arguments of
            :class:`~amuled_ma.beliefs.ollama.OllamaSource` (``num_predict``, ``num_ctx``,
            ``reasoning``, ``seed``, ``retries``, ...), checked against its signature.
        agents: A belief source per panel member, ``{agent: table}`` from the
            ``[feedback.agents.<agent>]`` tables: ``source`` = ``replay``, ``ollama``,
            ``rules``, ``terminal``, ``entry-point`` or ``policy`` and that kind's keys
            (:data:`amuled_ma.beliefs.routing.AGENT_KEYS`); an agent without a table uses
            ``source``. Checked on load by
            :func:`amuled_ma.beliefs.routing.check_agent_tables` (see ``docs/beliefs.md``).
        clusters_dirs: Folders of user cluster files (relative to the scenario file),
            loaded after the shipped ones; a file overrides a shipped cluster of its name.
        max_abstention: The largest share of rewarded steps one panel agent may leave
            unanswered (abstained, timeout, error, replay miss); beyond it the run stops
            with an error naming the agent, its source and the fix (judged once the agent
            was asked 20 distinct states).
        name: The fine-tune's variant name (folder ``finetune-<name>``); empty: named
            after the feedback (``finetune-amuled``).
        distill: ``[feedback.distill]``, the panel asked on a budget and a distilled
            reward model for the rest (:class:`DistillConfig`; off by default).

    """

    section: ClassVar[str] = "feedback"

    source: FeedbackSource = "replay"
    recording: str = ""
    model: str = ""
    host: str = ""
    hosts: list[str] = Field(default_factory=list)
    concurrency: int = Field(
        4, ge=1, le=1024, description="LLM requests in flight, one connection each"
    )
    timeout_s: float = Field(
        120.0,
        gt=0,
        le=86_400,
        description="seconds per LLM request: 0 fails all, above a day hangs",
    )
    miss_policy: MissPolicy = "uniform"
    cluster_recording: str = ""
    store: str = "beliefs.sqlite"
    clusters: list[str] = Field(default_factory=lambda: list(PAPER_CLUSTERS))
    fusion: str = "bjs-dst"
    ollama: dict[str, Any] = Field(default_factory=dict)
    agents: dict[str, dict[str, Any]] = Field(default_factory=dict)
    clusters_dirs: list[str] = Field(default_factory=list)
    max_abstention: float = Field(
        0.2,
        ge=0,
        le=1,
        description="share of rewarded steps an agent may leave unanswered before a run stops",
    )
    name: str = ""
    distill: DistillConfig = Field(default_factory=DistillConfig)

    @field_validator("host")
    @classmethod
    def _host_is_a_url(cls, value: str, info: ValidationInfo) -> str:
        if value:
            from amuled_ma.beliefs.hosts import normalize_host

            normalize_host(value, where=f"{_source(info)}: key [feedback].host")
        return value

    @field_validator("hosts")
    @classmethod
    def _hosts_are_urls(cls, value: list[str], info: ValidationInfo) -> list[str]:
        if value:
            from amuled_ma.beliefs.hosts import normalize_hosts

            normalize_hosts(value, where=f"{_source(info)}: key [feedback].hosts")
            if info.data.get("host"):
                raise ScenarioError(
                    f"{_source(info)}: keys [feedback].host ({info.data['host']!r}) and "
                    f"[feedback].hosts ({value!r}) are both set; give one server with host, "
                    'or a pool with hosts = [...] and host = "" (list that server in hosts '
                    'too; on the command line: --set feedback.host="")'
                )
        return value

    @field_validator("ollama")
    @classmethod
    def _ollama_is_finite(cls, value: Any, info: ValidationInfo) -> Any:
        return _finite_table("feedback", value, info)

    @field_validator("agents", mode="before")
    @classmethod
    def _agent_tables(cls, value: Any, info: ValidationInfo) -> Any:
        """Check the tables before their type, so that the messages name the table and fix."""
        _finite_table("feedback", value, info)
        if all(k in info.data for k in ("clusters", "source", "model")):  # else: reported
            from amuled_ma.beliefs.routing import check_agent_tables

            check_agent_tables(
                value,
                where=_source(info),
                clusters=info.data["clusters"],
                default_source=info.data["source"],
                default_model=info.data["model"],
            )
        return value


class EvaluationConfig(_Section):
    """Evaluation protocol.

    Attributes:
        episodes: Episodes per policy and mode.
        seed: Seed of the evaluation episodes (distinct from training seeds).
        modes: ``greedy`` and/or ``sampled`` action selection.
        confidence: Confidence level of the reported intervals.

    """

    section: ClassVar[str] = "evaluation"

    episodes: int = Field(
        50,
        ge=1,
        le=1_000_000,
        description="episodes run as parallel task copies (paper: 50); also checked against memory",
    )
    seed: int = Field(10_000, ge=0, le=MAX_SEED, description=_SEED_WHY)
    modes: list[EvaluationMode] = Field(default_factory=lambda: ["greedy", "sampled"])
    confidence: float = Field(
        0.95,
        gt=0,
        lt=1,
        description="two-sided confidence level; 1 would need an infinite interval",
    )

    @model_validator(mode="after")
    def _episodes_fit_in_memory(self, info: ValidationInfo) -> EvaluationConfig:
        _check_budget("evaluation", dict(self), _source(info))
        return self


class OutputConfig(_Section):
    """Where runs go.

    Attributes:
        runs_dir: Folder holding one sub-folder per run.
        tensorboard: Write TensorBoard event files.

    """

    section: ClassVar[str] = "output"

    runs_dir: str = "runs"
    tensorboard: bool = True


_M = TypeVar("_M", bound=BaseModel)


def _validate(model: type[_M], data: Any, source: str, loc: tuple[str, ...] = ()) -> _M:
    """``model.model_validate(data)`` with ``source`` in the context and errors converted."""
    context = {"source": source}
    token = _CONTEXT.set(context)
    try:
        return model.model_validate(data, context=context)
    except ValidationError as error:
        raise scenario_error(error, source, loc) from None
    finally:
        _CONTEXT.reset(token)


class Scenario(BaseModel):
    """A whole experiment setup.

    Built in code (``Scenario(name="x")``) it is validated like a file; a failure raises
    :class:`~amuled_ma.errors.ScenarioError`. ``model_copy(update=...)`` copies without
    validating; :meth:`replace` validates.

    Attributes:
        name: Scenario name (the file stem unless ``name`` is set at top level); it names
            the run folder, so it must be one safe path component (:data:`NAME_RULE`).
        path: The file it was loaded from (None when built in code).
        task: See :class:`TaskConfig`.
        ppo: See :class:`PPOConfig`.
        base: See :class:`BaseConfig`.
        finetune: See :class:`FinetuneConfig`.
        feedback: See :class:`FeedbackConfig`.
        evaluation: See :class:`EvaluationConfig`.
        output: See :class:`OutputConfig`.

    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    name: str = "scenario"
    path: Path | None = None
    task: TaskConfig = Field(default_factory=TaskConfig)
    ppo: PPOConfig = Field(default_factory=PPOConfig)
    base: BaseConfig = Field(default_factory=BaseConfig)
    finetune: FinetuneConfig = Field(default_factory=FinetuneConfig)
    feedback: FeedbackConfig = Field(default_factory=FeedbackConfig)
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)

    def __init__(self, /, **data: Any) -> None:
        _init(self, data, ())

    @field_validator("name")
    @classmethod
    def _name_is_a_folder_name(cls, value: str, info: ValidationInfo) -> str:
        return check_path_component(value, f"{_source(info)}: key name")

    @property
    def base_dir(self) -> Path:
        """Folder that relative paths of this scenario are resolved against."""
        return self.path.parent if self.path is not None else Path.cwd()

    def resolve(self, value: str) -> Path:
        """Resolve a path from this scenario against its folder."""
        path = Path(os.path.expandvars(os.path.expanduser(value)))
        return path if path.is_absolute() else (self.base_dir / path).resolve()

    def recording_path(self, *, required: bool = False) -> Path:
        """Find the replayed recording ``[feedback].recording``, by path or by name.

        ``recording`` is a path (``"../data/findmilk-gpt-4o-mini.json"``) or a bare name
        (``"findmilk-gpt-4o-mini"``, ``.json`` optional). Each place is searched for its file
        name, then (unless it ends in ``.json``) that name with ``.json`` added. The first
        existing file wins:

        1. the value as given, relative to the scenario file;
        2. ``$AMULED_RECORDINGS/<name>.json``;
        3. the user data folder, :func:`user_recordings_dir` (where
           ``amuled import authors PATH`` writes);
        4. ``../shared/amuled-recordings/<name>.json`` beside the repository checkout
           (the nearest folder with ``.git``) that holds the current directory.

        Args:
            required: Raise when no place holds the file. Without it the value as given
                (resolved) is returned, as before this lookup existed, so callers that
                test ``.exists()`` keep working.

        Returns:
            The recording file.

        Raises:
            ScenarioError: ``required`` and nothing was found (or the value is empty); the
                message lists every place looked and names ``amuled import authors PATH``.

        """
        value = self.feedback.recording
        as_given = self.resolve(value)
        where = self.path or f"scenario {self.name!r}"
        if not value.strip():
            if required:
                raise ScenarioError(
                    f"{where}: [feedback].recording is empty; name a recording file, or a "
                    "recording by name such as 'findmilk-gpt-4o-mini'"
                )
            return as_given
        names = [Path(value).name]
        if not value.endswith(".json"):
            names.append(f"{names[0]}.json")
        given = [as_given.with_name(n) for n in names]
        env = os.environ.get("AMULED_RECORDINGS")
        cwd = Path.cwd().resolve()
        root = next((d for d in (cwd, *cwd.parents) if (d / ".git").exists()), None)
        folders = [
            ("$AMULED_RECORDINGS", Path(os.path.expanduser(env)) if env else None, "not set"),
            ("the user data folder", user_recordings_dir(), ""),
            (
                "beside the checkout",
                root.parent / "shared" / "amuled-recordings" if root else None,
                "the current directory is in no checkout",
            ),
        ]
        candidates = given + [f / n for _, f, _ in folders if f is not None for n in names]
        for path in candidates:
            if path.is_file():
                return path
        if not required:
            return as_given
        looked = "; ".join(
            [f"as given (relative to the scenario file): {' or '.join(map(str, given))}"]
            + [
                f"{label}: {folder / names[-1] if folder is not None else f'({why})'}"
                for label, folder, why in folders
            ]
        )
        raise ScenarioError(
            f"{where}: [feedback].recording {value!r} not found; looked in: {looked}. Fix: "
            "convert the AMULED authors' recordings with 'amuled import authors PATH' "
            "(PATH = a checkout of https://github.com/temetski/moral_agent), or set "
            f"AMULED_RECORDINGS to the folder holding {names[-1]}"
        )

    def to_dict(self) -> dict[str, Any]:
        """Return the fully resolved scenario as plain data (for ``config.json``).

        Every section's keys (defaults filled in), the ``name`` and the ``path`` (a string,
        or None). :func:`scenario_from_dict` builds the scenario back from it once ``path``
        is taken out.
        """
        data = self.model_dump()
        data["path"] = str(self.path) if self.path else None
        return data

    def settings(self) -> dict[str, Any]:
        """Return the validated settings as plain JSON data, for comparing two scenarios.

        ``{section: {key: value}}`` for the seven sections (``task``, ``ppo``, ``base``,
        ``finetune``, ``feedback``, ``evaluation``, ``output``), every key present with
        defaults filled in, values as JSON types (``model_dump(mode="json")``: lists, not
        tuples; floats stay floats, so ``lambda_kl = 3`` and ``3.0`` compare equal). Left
        out: ``name`` and ``path``, which say where a scenario lives and where its runs go,
        not what a run learns. Paths inside the sections (``recording``, ``store``,
        ``runs_dir``) are kept as written, not resolved. Two scenarios with equal
        ``settings()`` train and evaluate alike; a resume check compares the saved
        ``settings()`` (or the part of it a variant depends on) with the current one.

        Returns:
            A new dict of JSON-serialisable data (``json.dumps`` takes it as it is).

        """
        return self.model_dump(mode="json", exclude={"name", "path"})

    def replace(self, section: str, **changes: Any) -> Scenario:
        """Return a copy with some keys of one section changed, validated like a file.

        Args:
            section: The section (``"finetune"``).
            **changes: New values by key (``lambda_kl=1.0``).

        Returns:
            The new scenario; this one is unchanged.

        Raises:
            ScenarioError: An unknown section or key, or a value of the wrong type or out of
                its range; the message names ``<file> (override of [section])``.

        """
        source = f"{self.path or self.name} (override of [{section}])"
        model = _SECTIONS.get(section)
        if model is None:
            raise ScenarioError(_unknown_section(section, source))
        current = getattr(self, section)
        merged = {key: getattr(current, key) for key in type(current).model_fields}
        for key, value in changes.items():
            head, dot, rest = key.partition(".")
            if not dot:
                merged[key] = value
                continue
            table = merged.get(head)
            if not isinstance(table, BaseModel | dict):
                close = _did_you_mean(head, list(merged))
                where = (
                    f"[{section}].{head} is not a table"
                    if head in merged
                    else f"no key [{section}].{head}{close}"
                )
                raise ScenarioError(f"{source}: key [{section}].{key}: {where}")
            merged[head] = _with_nested(table, rest, value)
        new_section = _validate(model, merged, source, (section,))
        return self.model_copy(update={section: new_section})

    def default_run_dir(self, runs_dir: str | os.PathLike[str] | None = None) -> Path:
        """Return ``<runs_dir>/<name>``, guaranteed to lie directly inside ``runs_dir``.

        Args:
            runs_dir: The folder of runs (default: ``[output].runs_dir``, relative to the
                current directory as before).

        Returns:
            The run directory, relative when ``runs_dir`` is.

        Raises:
            ScenarioError: The name is not a safe path component (see :func:`safe_child`).

        """
        root = self.output.runs_dir if runs_dir is None else runs_dir
        return safe_child(root, self.name, what=f"{self.path or '<scenario>'}: key name")


def _with_nested(table: BaseModel | dict[str, Any], key: str, value: Any) -> dict[str, Any]:
    """A nested table's keys as a dict, with ``key`` (dotted for deeper tables) set."""
    data = (
        {k: getattr(table, k) for k in type(table).model_fields}
        if isinstance(table, BaseModel)
        else dict(table)
    )
    head, dot, rest = key.partition(".")
    if dot and isinstance(data.get(head), BaseModel | dict):
        data[head] = _with_nested(data[head], rest, value)
    else:
        data[key] = value
    return data


#: The section models by table name, in the order of a scenario file.
_SECTIONS: dict[str, type[_Section]] = {
    "task": TaskConfig,
    "ppo": PPOConfig,
    "base": BaseConfig,
    "finetune": FinetuneConfig,
    "feedback": FeedbackConfig,
    "evaluation": EvaluationConfig,
    "output": OutputConfig,
}


# --------------------------------------------------------------------- user data
#: Folder name of our files in the XDG data folder (``~/.local/share/amuled-ma``).
USER_DATA_NAME = "amuled-ma"


def user_data_dir() -> Path:
    """The user data folder: ``$AMULED_DATA``, else ``$XDG_DATA_HOME/amuled-ma``.

    ``$XDG_DATA_HOME`` defaults to ``~/.local/share``. Imported recordings live in its
    ``recordings/`` sub-folder (:func:`user_recordings_dir`).
    """
    env = os.environ.get("AMULED_DATA")
    if env:
        return Path(os.path.expanduser(env))
    xdg = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(os.path.expanduser(xdg)) / USER_DATA_NAME


def user_recordings_dir() -> Path:
    """Folder of the user's recordings: ``<user_data_dir()>/recordings``."""
    return user_data_dir() / "recordings"


# --------------------------------------------------------------------- path components
def _component_problem(name: str) -> str | None:
    """What makes ``name`` unsafe as one path component (None: nothing)."""
    if not name:
        return "it is empty"
    if len(name) > MAX_NAME_LENGTH:
        return f"it has {len(name)} characters"
    for bad in ("/", "\\", ":", os.sep, os.altsep or "/"):
        if bad in name:
            return f"it contains {bad!r}"
    if ".." in name:
        return "it contains '..'"
    for ch in name:
        if ord(ch) < 32 or 127 <= ord(ch) < 160:
            return f"it contains the control character U+{ord(ch):04X}"
    if name[0] in ".-":
        return f"it starts with {name[0]!r}"
    if name != name.strip():
        return "it has a leading or trailing space"
    return None


def check_path_component(name: object, where: str) -> str:
    """Check that ``name`` can be used as one folder name, and return it.

    Args:
        name: The value (a scenario name, a task name).
        where: File and key, for the error (``"s.toml: key name"``).

    Returns:
        ``name`` unchanged.

    Raises:
        ScenarioError: ``name`` is not a string, or is empty, too long, or holds a path
            separator, ``..``, a colon, a control character, a leading ``.``/``-`` or
            a leading or trailing space.

    """
    if not isinstance(name, str):
        raise ScenarioError(f"{where} expects string, found {_found_name(name)} ({name!r})")
    problem = _component_problem(name)
    if problem:
        raise ScenarioError(
            f"{where} is used as a folder name and must be one safe path component "
            f"({NAME_RULE}); found {name!r}: {problem}"
        )
    return name


def safe_child(root: str | os.PathLike[str], name: str, *, what: str = "name") -> Path:
    """Return ``root / name`` after checking that it lies directly inside ``root``.

    ``name`` must pass :func:`check_path_component`; the joined path is then normalised
    (without following symbolic links, so a run folder the user linked elsewhere on
    purpose keeps working) and must have ``root`` as its parent.

    Args:
        root: The folder the child must stay in (``[output].runs_dir``).
        name: The child's name.
        what: File and key of ``name``, for the error.

    Returns:
        ``Path(root) / name``, relative when ``root`` is.

    Raises:
        ScenarioError: ``name`` is unsafe, or the path would leave ``root``.

    """
    check_path_component(name, what)
    child = Path(root) / name
    parent = Path(os.path.normpath(os.path.abspath(root)))
    if Path(os.path.normpath(os.path.abspath(child))).parent != parent:
        raise ScenarioError(  # pragma: no cover - the component check already stops this
            f"{what}: {name!r} would put the run outside {parent}; expected a single "
            f"folder name ({NAME_RULE})"
        )
    return child


# ----------------------------------------------------------------------- number ranges
def physical_memory_bytes() -> int:
    """Physical memory of this machine (``FALLBACK_MEMORY_BYTES`` where unknown)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return FALLBACK_MEMORY_BYTES
    return total if total > 0 else FALLBACK_MEMORY_BYTES


def _bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError  # pragma: no cover


def _kind(number_type: Any, rng: Range) -> str:
    """What a key of ``number_type`` (``int`` or ``float``) in ``rng`` is, in words."""
    if number_type is int:
        if rng.low is not None and rng.low >= 1:
            return "a positive integer"
        if rng.low == 0:
            return "a non-negative integer"
        return "an integer"
    return "a finite number"


def _check_finite(key: str, value: Any, source: str) -> None:
    """Refuse NaN and infinities anywhere in a free-form value (``options``, ``ollama``)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ScenarioError(f"{source}: key {key} expects a finite number, found {value!r}")
    if isinstance(value, dict):
        for k, v in value.items():
            _check_finite(f"{key}.{k}", v, source)
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            _check_finite(f"{key}[{i}]", v, source)


def _check_memory(
    key: str, count: int, unit: int, what: str, source: str, hint: Callable[[int], str]
) -> None:
    """Refuse ``count`` items of ``unit`` bytes beyond ``MEMORY_FRACTION`` of the memory."""
    memory = physical_memory_bytes()
    budget = MEMORY_FRACTION * memory
    need = count * unit
    if need > budget:
        limit = int(budget // unit)
        raise ScenarioError(
            f"{source}: key {key} = {count:,} {what} need about {_bytes(need)} "
            f"({unit:,} bytes each, estimated) but at most {MEMORY_FRACTION:.0%} of this "
            f"machine's {_bytes(memory)} of memory may be used; expected at most {limit:,} "
            f"{what}{hint(limit)}"
        )


def _network_parameters(hidden_dims: list[int]) -> int:
    dims = [ASSUMED_OBS_DIM, *hidden_dims, ASSUMED_NUM_ACTIONS]
    return sum(a * b + b for a, b in itertools.pairwise(dims))


def _check_budget(section: str, values: dict[str, Any], source: str) -> None:
    """Checks across keys of one section: memory estimates and the run-length cap."""
    if section in ("base", "finetune"):
        envs, steps = values["num_envs"], values["num_steps_per_env"]
        _check_memory(
            f"[{section}].num_envs x [{section}].num_steps_per_env = {envs:,} x {steps:,}",
            envs * steps,
            BYTES_PER_TRANSITION,
            "rollout transitions",
            source,
            lambda limit: (
                f" (e.g. num_envs <= {max(limit // steps, 0):,} at "
                f"num_steps_per_env = {steps:,}), found num_envs = {envs!r}"
            ),
        )
    if section == "finetune":
        its, envs, steps = values["iterations"], values["num_envs"], values["num_steps_per_env"]
        total = its * envs * steps
        if total > MAX_ENV_STEPS:
            raise ScenarioError(
                f"{source}: key [finetune].iterations x num_envs x num_steps_per_env = "
                f"{its:,} x {envs:,} x {steps:,} = {total:,} env steps; expected at most "
                f"MAX_ENV_STEPS = {MAX_ENV_STEPS:,} env steps (the cap on one run, about "
                f"28 hours at 100,000 steps/s), found iterations = {its!r}"
            )
    if section == "ppo":
        _check_memory(
            f"[ppo].hidden_dims = {values['hidden_dims']!r} (actor and critic, "
            f"{ASSUMED_OBS_DIM} inputs, {ASSUMED_NUM_ACTIONS} outputs assumed)",
            _network_parameters(values["hidden_dims"]),
            BYTES_PER_PARAMETER,
            "network parameters",
            source,
            lambda _: " (use narrower or fewer hidden layers)",
        )
    if section == "evaluation":
        _check_memory(
            "[evaluation].episodes",
            values["episodes"],
            BYTES_PER_EPISODE,
            "evaluation episodes",
            source,
            lambda _: f", found {values['episodes']!r}",
        )


def _bounds(metadata: list[Any], why: str | None) -> Range | None:
    """The ``ge``/``gt``/``le``/``lt`` constraints among a field's metadata as a Range."""
    low = high = None
    low_open = high_open = False
    for item in metadata:
        if getattr(item, "ge", None) is not None:
            low = item.ge
        elif getattr(item, "gt", None) is not None:
            low, low_open = item.gt, True
        if getattr(item, "le", None) is not None:
            high = item.le
        elif getattr(item, "lt", None) is not None:
            high, high_open = item.lt, True
    if low is None and high is None:
        return None
    return Range(low, high, low_open, high_open, why or "")


def _item_field(annotation: Any) -> Any:
    """The ``Field`` of a list's items (``list[Annotated[int, Field(...)]]``), if any."""
    if typing.get_origin(annotation) is not list:
        return None
    (item,) = typing.get_args(annotation)
    if typing.get_origin(item) is not Annotated:
        return None
    return next((m for m in typing.get_args(item)[1:] if hasattr(m, "metadata")), None)


def field_range(model: type[BaseModel], key: str) -> Range | None:
    """The range of a numeric key, as declared by its ``Field`` bounds and description.

    Args:
        model: A section model (:class:`PPOConfig`).
        key: The key (``gamma``); for a list of numbers (``hidden_dims``), the range of
            each entry.

    Returns:
        The range, with the field's ``description`` as the reason; None for a key without
        bounds (a string, a flag, a free table).

    """
    info = model.model_fields[key]
    item = _item_field(info.annotation)
    if item is not None:
        return _bounds(item.metadata, item.description)
    return _bounds(info.metadata, info.description)


def field_length(model: type[BaseModel], key: str) -> Range | None:
    """The allowed length of a list key (``min_length``/``max_length``), if it has one.

    Args:
        model: A section model (:class:`PPOConfig`).
        key: The key (``hidden_dims``).

    Returns:
        The range of the number of entries, with the field's ``description`` as the
        reason; None when the length is free.

    """
    info = model.model_fields[key]
    low = next((m.min_length for m in info.metadata if hasattr(m, "min_length")), None)
    high = next((m.max_length for m in info.metadata if hasattr(m, "max_length")), None)
    if low is None and high is None:
        return None
    return Range(low, high, why=info.description or "")


def validate_section(section: str, values: dict[str, Any], source: str) -> _Section:
    """Validate one section's values as a file's table is validated, and build it.

    Types, choices, the declared ranges (:func:`field_range`), safe names, finite floats
    (also inside free tables), the memory estimates and the run-length cap: everything
    the section model checks.

    Args:
        section: Section name (``ppo``).
        values: Keys of the section, by name (keys left out take their defaults).
        source: The file (or ``--set`` override) the values came from, for errors.

    Returns:
        The section model (:class:`PPOConfig` for ``ppo``).

    Raises:
        ScenarioError: An unknown section or key, or a value of the wrong type or out of
            range; the message names the file, the ``[section].key``, what was expected
            (the range and why) and the value found.

    """
    model = _SECTIONS.get(section)
    if model is None:
        raise ScenarioError(_unknown_section(section, source))
    return _validate(model, values, source, (section,))


# ------------------------------------------------------------------------ error messages
def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Annotated:
        return _type_name(typing.get_args(tp)[0])
    if origin is list:
        (inner,) = typing.get_args(tp)
        return f"list of {_type_name(inner)}"
    if origin is dict:
        return "table"
    if origin is Literal:
        return f"string ({' or '.join(map(str, typing.get_args(tp)))})"
    if tp is float:
        return "float"
    if tp is int:
        return "integer"
    if tp is str:
        return "string"
    if tp is bool:
        return "boolean"
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return "table"
    return getattr(tp, "__name__", str(tp))


def _number_type(annotation: Any) -> Any:
    """``int`` or ``float`` of a number key or a list of numbers (``list[Annotated[int, ...]]``)."""
    if typing.get_origin(annotation) is list:
        annotation = typing.get_args(annotation)[0]
    if typing.get_origin(annotation) is Annotated:
        annotation = typing.get_args(annotation)[0]
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if len(args) == 1 and type(None) in typing.get_args(annotation):  # ``int | None``
        return args[0]
    return annotation


def _found_name(value: Any) -> str:
    return {
        bool: "boolean",
        int: "integer",
        float: "float",
        str: "string",
        list: "array",
        dict: "table",
    }.get(type(value), type(value).__name__)


def _float_for_int_hint(wants_int: bool, value: Any) -> str:
    """Explain a float written where an integer is expected (TOML reads ``1e8`` as float)."""
    floats = [v for v in (value if isinstance(value, list) else [value]) if isinstance(v, float)]
    if not wants_int or not floats:
        return ""
    example = next((v for v in floats if v.is_integer()), None)
    if example is None:
        return "; an integer is needed here"
    return (
        f"; TOML reads {example!r} (written with a decimal point or an exponent such as 1e8) "
        f"as a float: write the integer as {int(example):_}"
    )


def _did_you_mean(key: str, names: list[str]) -> str:
    close = difflib.get_close_matches(key, names, n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def _unknown_top_level(key: object, source: str) -> str:
    names = ["name", *_SECTIONS]
    return (
        f"{source}: unknown section or key {key!r}{_did_you_mean(str(key), names)}; expected "
        f"name or one of the tables {', '.join(f'[{s}]' for s in _SECTIONS)}"
    )


def _unknown_section(section: str, source: str) -> str:
    return (
        f"{source}: unknown section [{section}]{_did_you_mean(section, list(_SECTIONS))}; "
        f"expected one of {', '.join(f'[{s}]' for s in _SECTIONS)}"
    )


#: pydantic error types of a number outside its declared bounds (or NaN, infinite).
_RANGE_ERRORS = frozenset(
    {"greater_than", "greater_than_equal", "less_than", "less_than_equal", "finite_number"}
)


def _describe(error: Any, source: str, loc: tuple[Any, ...]) -> str:
    """One pydantic error (``loc`` from the scenario's top) as a scenario message."""
    kind, value = error["type"], error.get("input")
    found = f"found {_found_name(value)} ({value!r})"
    if not loc:
        return f"{source}: {error['msg']}, {found}"
    head = loc[0]
    if head not in _SECTIONS:  # a top-level key: name, or no key of a scenario file
        if kind == "extra_forbidden":
            return _unknown_top_level(head, source)
        if kind == "string_type":
            return f"{source}: key {head} expects string, {found}"
        return f"{source}: key {head}: {error['msg']}, {found}"
    section, model = str(head), _SECTIONS[str(head)]
    while len(loc) > 2 and _table_model(model, loc[1]) is not None:
        model = _table_model(model, loc[1])  # a nested table: [feedback.distill]
        section, loc = f"{section}.{loc[1]}", (loc[0], *loc[2:])
    if len(loc) == 1:
        if kind in ("model_type", "model_attributes_type", "dict_type"):
            return f"{source}: key {section} expects table, {found}"
        return f"{source}: key [{section}]: {error['msg']}, {found}"
    key, rest = str(loc[1]), loc[2:]
    names = list(model.model_fields)
    if kind == "extra_forbidden" and not rest:
        return (
            f"{source}: unknown key [{section}].{key}{_did_you_mean(key, names)}; expected one "
            f"of: {', '.join(names)}"
        )
    where = f"[{section}].{key}"
    info = model.model_fields.get(key)
    if info is None:  # pragma: no cover - pydantic reports only keys of the model
        return f"{source}: key {where}: {error['msg']}, {found}"
    index = rest[0] if rest and isinstance(rest[0], int) else None
    at = f" at index {index}" if index is not None else ""
    if kind in _RANGE_ERRORS:
        rng = field_range(model, key) or Range()
        number_type = _number_type(info.annotation)
        if index is not None:
            where += f"[{index}]"
        return (
            f"{source}: key {where} expects {_kind(number_type, rng)} {rng.describe()} "
            f"({rng.why}), found {value!r}"
        )
    if kind in ("too_short", "too_long"):
        length = field_length(model, key) or Range()
        return (
            f"{source}: key {where} expects a list whose length is {length.describe()} "
            f"({length.why}), found {len(value)} entries ({value!r})"
        )
    if kind == "literal_error":
        tp = info.annotation if index is None else typing.get_args(info.annotation)[0]
        choices = ", ".join(map(str, typing.get_args(tp)))
        each = "each entry to be " if index is not None else ""
        return f"{source}: key {where} expects {each}one of {choices}, found {value!r}{at}"
    if kind.endswith("_type"):
        wants_int = kind == "int_type"
        return (
            f"{source}: key {where} expects {_type_name(info.annotation)}, {found}{at}"
            f"{_float_for_int_hint(wants_int, value)}"
        )
    return f"{source}: key {where}{at}: {error['msg']}, {found}"


def _table_model(model: type[BaseModel], key: Any) -> type[BaseModel] | None:
    """The model of ``model``'s key when that key is a nested table, else None."""
    info = model.model_fields.get(str(key))
    tp = info.annotation if info is not None else None
    return tp if isinstance(tp, type) and issubclass(tp, BaseModel) else None


def scenario_error(error: ValidationError, source: str, loc: tuple[str, ...] = ()) -> ScenarioError:
    """Turn pydantic's :class:`~pydantic.ValidationError` into one scenario error line.

    The first problem pydantic found (in the order of the file's sections and keys) is
    described from its ``loc`` (section, key, list index), ``type`` (which check failed),
    ``input`` (the value found) and ``ctx``, with the key's declared range and reason
    (:func:`field_range`) or choices; an unknown key names the close match. A validator's
    own :class:`~amuled_ma.errors.ScenarioError` (a safe name, the agent tables, memory)
    is returned as it is. Further problems are counted at the end.

    Args:
        error: The error of ``model_validate`` (or of a model's construction).
        source: The file (or ``--set`` override) validated, named first in the message.
        loc: Where the validated model sits in a scenario: ``("ppo",)`` for a section
            model, ``()`` for a whole :class:`Scenario`.

    Returns:
        ``ScenarioError("<source>: key [section].key expects <what>, found <value>")``.

    """
    problems = error.errors(include_url=False)
    first = problems[0]
    cause = (first.get("ctx") or {}).get("error")
    if isinstance(cause, ScenarioError):
        return cause
    message = _describe(first, source, (*loc, *first["loc"]))
    more = len(problems) - 1
    if more:
        message += f" (and {more} more problem{'s' if more > 1 else ''})"
    return ScenarioError(message)


# ---------------------------------------------------------------------------- loading
def scenario_from_dict(data: dict[str, Any], *, path: Path | None = None) -> Scenario:
    """Build and validate a :class:`Scenario` from parsed TOML data.

    Args:
        data: The parsed TOML document (or :meth:`Scenario.to_dict` without ``path``).
        path: The file it came from (used in errors and to resolve relative paths).

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: Unknown section or key, a value of the wrong type or out of its
            range (see :func:`field_range`), or a name that is no safe folder name.

    """
    source = str(path) if path is not None else "<scenario>"
    if "path" in data:  # a field of Scenario, but never a key of a scenario file
        raise ScenarioError(_unknown_top_level("path", source))
    values = dict(data)
    if "name" not in values:
        stem = path.stem if path is not None else "scenario"
        values["name"] = check_path_component(
            stem, f"{source}: the scenario name (the file name, as no top-level name is set)"
        )
    return _validate(Scenario, {**values, "path": path}, source)


def resolve_scenario_path(name_or_path: str | os.PathLike[str]) -> Path:
    """Find a scenario file from a path or the name of a shipped scenario.

    Args:
        name_or_path: A path to a TOML file, or a shipped scenario's name (``findmilk``).

    Returns:
        The absolute path of the file.

    Raises:
        ScenarioError: Neither an existing file nor a shipped scenario.

    """
    path = Path(name_or_path).expanduser()
    if path.is_file():
        return path.resolve()
    shipped = scenarios_dir()
    for candidate in (shipped / str(name_or_path), shipped / f"{name_or_path}.toml"):
        if candidate.is_file():
            return candidate.resolve()
    available = ", ".join(sorted(p.stem for p in shipped.glob("*.toml")))
    raise ScenarioError(
        f"scenario {str(name_or_path)!r} not found: not a file, and not a shipped scenario "
        f"(shipped: {available or 'none'} in {shipped})"
    )


def load_scenario(name_or_path: str | os.PathLike[str]) -> Scenario:
    """Load and validate a scenario from a TOML file or a shipped scenario's name.

    Args:
        name_or_path: File path or shipped name (``findmilk``, ``driving``).

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: The file is missing, is not valid TOML, or fails validation.

    """
    path = resolve_scenario_path(name_or_path)
    try:
        data = tomllib.loads(read_text(path, "scenario", ScenarioError))
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{path}: not valid TOML: {error}") from None
    return scenario_from_dict(data, path=path)
