"""The sections of a scenario file, one frozen, strict pydantic v2 model per table."""

from __future__ import annotations

import math
from contextvars import ContextVar
from typing import Annotated, Any, ClassVar, Literal, TypeVar, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_serializer,
    field_validator,
    model_validator,
)

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.agents import (
    AgentSpec,
    Concurrency,
    OllamaSpec,
    TimeoutS,
    check_agent_tables,
)
from amuled_ma.scenario.memory import (
    MAX_ENV_STEPS,
    MAX_SEED,
    check_budget,
    check_distill_memory,
    check_finite,
)
from amuled_ma.scenario.messages import BUILT_IN_CODE, SECTIONS, scenario_error
from amuled_ma.scenario.panel_checks import check_clusters, check_fusion, prior_rules
from amuled_ma.scenario.paths import check_path_component
from amuled_ma.scenario.ranges import found
from amuled_ma.scenario.task_options import check_task_options
from amuled_ma.servers.urls import normalize_host, normalize_hosts

#: The five moral clusters of the paper (Table 1), in the recordings' order.
PAPER_CLUSTERS = ("consequentialist", "deontological", "virtue", "care", "social_justice")

#: ``[feedback].source``: the belief source of agents without a ``[feedback.agents]`` table.
FeedbackSource = Literal["replay", "ollama", "rules"]
#: ``[feedback].miss_policy``: what a replay miss gives.
MissPolicy = Literal["uniform", "fallback", "error", "zero"]
#: ``[finetune].recipe``: how the KL anchor enters the fine-tuning reward.
Recipe = Literal["equation", "authors"]
#: ``[base]``, ``[finetune].grad_clip``: each network clipped apart (rsl-rl) or jointly (CleanRL).
GradClip = Literal["per_network", "joint"]
#: ``[ppo].activation``: rsl-rl's names of the hidden activation.
Activation = Literal["tanh", "relu", "elu", "selu", "lrelu", "sigmoid", "identity"]
#: ``[evaluation].modes``: action selection of the evaluation episodes.
EvaluationMode = Literal["greedy", "sampled"]
EVALUATION_MODES: tuple[EvaluationMode, ...] = get_args(EvaluationMode)
#: ``[feedback.distill].model``: the distilled reward model's kind.
DistillModel = Literal["mlp"]
#: ``[feedback.distill].selection``: which new states the budget spends on.
DistillSelection = Literal["uncertainty", "random"]


# Reasons of ranges shared by several keys (each key's ``Field(description=...)``).
_SEED_WHY = "a seed of torch and of the tasks' 64-bit random streams"
_EPOCHS_WHY = "optimisation passes over each rollout; CleanRL 4, authors 16"
_LR_WHY = "Adam step size: 0 learns nothing, beyond 1 the update diverges"
_SAVE_WHY = "iterations between checkpoints; 0 would divide by zero"
_ENVS_WHY = "parallel copies; with num_steps_per_env also checked against memory"
_STEPS_WHY = "rollout length per copy; with num_envs also checked against memory"
_WEIGHT_WHY = "a weight; negative flips the term's sign"


#: The validation context (``{"source": <file or override>}``) of the scenario being
#: validated: pydantic calls a model's own ``__init__`` without ``model_validate``'s context,
#: so `validate_model` also sets it here for `_init` (pydantic's documented pattern).
_CONTEXT: ContextVar[dict[str, str] | None] = ContextVar("amuled_scenario_context", default=None)


def _init(model: BaseModel, data: dict[str, Any], loc: tuple[str, ...]) -> None:
    """Validate ``data`` into ``model`` (the models' ``__init__``; errors: `ScenarioError`)."""
    context = _CONTEXT.get()
    try:
        model.__pydantic_validator__.validate_python(data, self_instance=model, context=context)
    except ValidationError as error:
        if context is not None:
            raise
        raise scenario_error(error, BUILT_IN_CODE, loc) from None


def _source(info: ValidationInfo) -> str:
    """The file (or override) being validated: the validation context's ``source``."""
    return str((info.context or {}).get("source", BUILT_IN_CODE))


class _Section(BaseModel):
    """Base of the section models: strict, frozen, no unknown keys, no NaN; validated when built."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    #: The table's name in a scenario file (``task`` for ``[task]``, ``feedback.distill``).
    section: ClassVar[str] = ""

    def __init__(self, /, **data: object) -> None:
        _init(self, data, tuple(self.section.split(".")))

    @model_validator(mode="after")
    def _within_budget(self, info: ValidationInfo) -> _Section:
        """Checks across keys (memory estimates, the run-length cap; `check_budget`)."""
        check_budget(self.section, dict(self), _source(info))
        return self


def _finite_table(section: str, value: object, info: ValidationInfo) -> object:
    """Refuse NaN and infinities anywhere in a free-form table, naming the nested key."""
    check_finite(f"[{section}].{info.field_name}", value, _source(info))
    return value


class TaskConfig(_Section):
    """The task: its name, base seed, ``max_steps`` (0: the task's default) and ``options``."""

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
    def _options_are_the_tasks(cls, value: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        _finite_table("task", value, info)
        name = info.data.get("name")  # validated before: absent when it was refused
        if isinstance(name, str):  # before any folder: the task itself refuses them late
            check_task_options(name, value, _source(info))
        return value


class PPOConfig(_Section):
    """PPO hyperparameters shared by base training and fine-tuning (CleanRL ``ppo.py`` defaults).

    ``normalize_advantage_per_mini_batch``: per mini-batch (CleanRL) rather than per rollout.
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


class BaseConfig(_Section):
    """Base training: ``r = r_env + c * r_shaping``, ``c`` = ``shaping_coef`` (``base`` uses 0).

    ``reshuffle_each_epoch``: a new mini-batch partition every epoch (CleanRL), else one per
    update (rsl-rl); ``bootstrap_time_outs``: add ``gamma * V(s)`` at a truncation (rsl-rl),
    else close it like a termination (CleanRL).
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
    grad_clip: GradClip = "per_network"
    reshuffle_each_epoch: bool = False
    bootstrap_time_outs: bool = True


class FinetuneConfig(_Section):
    """Fine-tuning on fused feedback: ``r = -lambda_kl * KL(pi || pi_base) + f(B)[a]``.

    Epochs, learning rate and annealing override ``[ppo]``; ``recipe``: the KL anchor,
    ``"equation"`` (the paper's ``log pi(a|s) - log pi_base(a|s)``) or ``"authors"``.
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
    grad_clip: GradClip = "per_network"
    reshuffle_each_epoch: bool = False
    bootstrap_time_outs: bool = True


class DistillConfig(_Section):
    """``[feedback.distill]``: LLM feedback on a budget (``docs/distill.md``).

    ``budget``: a float in ``(0, 1]`` asks at most ``max(1, floor(budget x visited))`` distinct
    states, an integer that many; ``answer_misses``: the model answers replay misses and
    abstentions (``distilled_miss``); ``seed`` unset: the job's training seed.
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

    @field_validator("budget", mode="before")
    @classmethod
    def _budget_is_a_share_or_a_count(cls, value: object, info: ValidationInfo) -> object:
        ok = not isinstance(value, bool) and (
            (isinstance(value, int) and value >= 1)
            or (isinstance(value, float) and math.isfinite(value) and 0 < value <= 1)
        )
        if not ok:
            raise ScenarioError(
                f"{_source(info)}: key [feedback.distill].budget expects a share in (0, 1] "
                "written as a float (0.1: at most 10% of the distinct states visited are "
                "asked) or a count >= 1 written as an integer (at most that many distinct "
                f"states), found {found(value)}"
            )
        return value


class FeedbackConfig(_Section):
    """Where beliefs come from and how they are fused (``docs/beliefs.md``, ``docs/ollama.md``).

    ``host`` empty: ``$OLLAMA_HOST``, else ``http://127.0.0.1:11434``; ``cluster_recording``:
    what the ``clusters`` and ``aggregation`` ablations replay when ``recording`` keeps only
    fused beliefs; ``weights``: a panel weights file, a prior on the ``amuled`` variant's
    members; ``agents``: ``[feedback.agents.<agent>]`` (an agent without one uses ``source``);
    ``name``: the fine-tune's variant name (folder ``finetune-<name>``).
    """

    section: ClassVar[str] = "feedback"

    source: FeedbackSource = "replay"
    recording: str = ""
    model: str = ""
    host: str = ""
    hosts: list[str] = Field(default_factory=list)
    concurrency: Concurrency = 4
    timeout_s: TimeoutS = 120.0
    miss_policy: MissPolicy = "uniform"
    cluster_recording: str = ""
    store: str = "beliefs.sqlite"
    clusters: list[str] = Field(default_factory=lambda: list(PAPER_CLUSTERS))
    fusion: str = "bjs-dst"
    weights: str = ""
    ollama: dict[str, Any] = Field(default_factory=dict)
    agents: dict[str, AgentSpec] = Field(default_factory=dict)
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
            normalize_host(value, where=f"{_source(info)}: key [feedback].host")
        return value

    @field_validator("hosts")
    @classmethod
    def _hosts_are_urls(cls, value: list[str], info: ValidationInfo) -> list[str]:
        if value:
            normalize_hosts(value, where=f"{_source(info)}: key [feedback].hosts")
            if info.data.get("host"):
                raise ScenarioError(
                    f"{_source(info)}: keys [feedback].host ({info.data['host']!r}) and "
                    f"[feedback].hosts ({value!r}) are both set; give one server with host, "
                    'or a pool with hosts = [...] and host = "" (list that server in hosts '
                    'too; on the command line: --set feedback.host="")'
                )
        return value

    @field_validator("clusters")
    @classmethod
    def _clusters_are_a_panel(cls, value: list[str], info: ValidationInfo) -> list[str]:
        return check_clusters(value, _source(info))

    @field_validator("fusion")
    @classmethod
    def _fusion_is_a_rule(cls, value: str, info: ValidationInfo) -> str:
        return check_fusion(value, info.data.get("clusters"), _source(info))

    @field_validator("weights")
    @classmethod
    def _weights_need_a_prior_rule(cls, value: str, info: ValidationInfo) -> str:
        fusion = info.data.get("fusion")
        rules = prior_rules()
        if value.strip() and fusion is not None and fusion not in rules:
            raise ScenarioError(
                f"{_source(info)}: key [feedback].weights ({value!r}) is a prior on the "
                f"panel's members, which only the rules {', '.join(rules)} take, but "
                f"[feedback].fusion is {fusion!r}; set fusion to one of them (e.g. "
                'fusion = "bjs-dst") or drop weights (weights = "")'
            )
        return value

    @field_validator("ollama")
    @classmethod
    def _ollama_is_finite(cls, value: dict[str, Any], info: ValidationInfo) -> object:
        """Refuse keys no ``OllamaSource`` takes, or that ``[feedback]`` sets itself."""
        own = {"source", "model", "host", "hosts", "concurrency", "timeout_s"}
        allowed = set(OllamaSpec.model_fields) - own
        unknown = sorted(set(value) - allowed)
        if unknown:
            raise ScenarioError(
                f"{_source(info)}: [feedback.ollama] unknown key(s) {', '.join(unknown)}; "
                f"expected some of {', '.join(sorted(allowed))}"
            )
        return _finite_table("feedback", value, info)

    @field_validator("agents", mode="before")
    @classmethod
    def _agent_tables(cls, value: object, info: ValidationInfo) -> object:
        """Validate the tables here, once, so that the messages name the table and the fix."""
        _finite_table("feedback", value, info)
        if not all(k in info.data for k in ("clusters", "source", "model")):
            return value  # a problem already reported
        return check_agent_tables(
            value,
            where=_source(info),
            clusters=info.data["clusters"],
            default_source=info.data["source"],
            default_model=info.data["model"],
        )

    @model_validator(mode="after")
    def _distilled_model_fits_in_memory(self, info: ValidationInfo) -> FeedbackConfig:
        d = self.distill
        if d.enabled:
            check_distill_memory(d.ensemble, d.hidden, len(self.clusters), d.budget, _source(info))
        return self

    @field_serializer("agents")
    def _agents_as_written(self, agents: dict[str, Any]) -> dict[str, Any]:
        """The tables as written (the keys each set), so ``to_dict`` round-trips."""
        return {
            name: {"source": spec.source, **spec.model_dump(exclude_unset=True)}
            for name, spec in agents.items()
        }


class EvaluationConfig(_Section):
    """Evaluation protocol: episodes per policy and mode, seed, modes, confidence level."""

    section: ClassVar[str] = "evaluation"

    episodes: int = Field(
        50,
        ge=1,
        le=1_000_000,
        description="episodes run as parallel task copies (paper: 50); also checked against memory",
    )
    seed: int = Field(10_000, ge=0, le=MAX_SEED, description=_SEED_WHY)
    modes: list[EvaluationMode] = Field(default_factory=lambda: list(EVALUATION_MODES))
    confidence: float = Field(
        0.95,
        gt=0,
        lt=1,
        description="two-sided confidence level; 1 would need an infinite interval",
    )


class OutputConfig(_Section):
    """Where runs go (``runs_dir``, a sub-folder per run); whether TensorBoard files are written."""

    section: ClassVar[str] = "output"

    runs_dir: str = "runs"
    tensorboard: bool = True


_M = TypeVar("_M", bound=BaseModel)


def validate_model(model: type[_M], data: object, source: str, loc: tuple[str, ...] = ()) -> _M:
    """Validate ``data`` into ``model`` as read from ``source``; ``loc``: where it sits.

    Raises:
        ScenarioError: One line naming ``source``, the first problem and how many more.
    """
    context = {"source": source}
    token = _CONTEXT.set(context)
    try:
        return model.model_validate(data, context=context)
    except ValidationError as error:
        raise scenario_error(error, source, loc) from None
    finally:
        _CONTEXT.reset(token)


SECTIONS.update(
    {
        "task": TaskConfig,
        "ppo": PPOConfig,
        "base": BaseConfig,
        "finetune": FinetuneConfig,
        "feedback": FeedbackConfig,
        "evaluation": EvaluationConfig,
        "output": OutputConfig,
    }
)
