"""Scenarios: everything one experiment needs, read from a TOML file and validated.

A scenario file has one table per concern (``[task]``, ``[ppo]``, ``[base]``,
``[finetune]``, ``[feedback]``, ``[evaluation]``, ``[output]``); each maps onto a
frozen dataclass below. Every key is checked on load: an unknown key or a value of
the wrong type raises :class:`~amuled_ma.errors.ScenarioError` naming the file, the
key, the expected type and the type found. Keys left out take the defaults below,
which follow the paper (Dubey, Dailisan, Mahajan, "AMULED") and CleanRL's PPO.

Relative paths in a scenario (recordings, belief store, output folder) are resolved
against the scenario file's folder, never the current directory. A shipped scenario
can be named without a path (``amuled run findmilk``): see :func:`resolve_scenario_path`.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from amuled_ma.errors import ScenarioError
from amuled_ma.resources import scenarios_dir

#: The five moral clusters of the paper (Table 1), in the recordings' order.
PAPER_CLUSTERS = ("consequentialist", "deontological", "virtue", "care", "social_justice")


@dataclass(frozen=True)
class TaskConfig:
    """The task environment.

    Attributes:
        name: Task name known to :func:`amuled_ma.tasks.get_task` (``findmilk``, ``driving``).
        seed: Base random seed of the run.
        max_steps: Episode step limit; 0 keeps the task's own default.
        options: Extra keyword options passed to the task constructor.

    """

    name: str = "findmilk"
    seed: int = 1
    max_steps: int = 0
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PPOConfig:
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

    hidden_dims: list[int] = field(default_factory=lambda: [64, 64])
    activation: str = "tanh"
    learning_rate: float = 2.5e-4
    anneal_lr: bool = True
    gamma: float = 0.99
    lam: float = 0.95
    clip_param: float = 0.2
    entropy_coef: float = 0.01
    value_loss_coef: float = 0.5
    max_grad_norm: float = 0.5
    num_learning_epochs: int = 4
    num_mini_batches: int = 4
    normalize_advantage_per_mini_batch: bool = True


@dataclass(frozen=True)
class BaseConfig:
    """Base training (paper, Simulation Studies): ``r = r_env + c * r_shaping``.

    Attributes:
        total_steps: Environment steps of the whole run (all copies together).
        num_envs: Parallel environment copies.
        num_steps_per_env: Rollout length per copy and iteration.
        shaping_coef: ``c`` of the ``shaped`` variant (the ``base`` variant uses 0).
        save_interval: Iterations between checkpoints.

    """

    total_steps: int = 500_000
    num_envs: int = 4
    num_steps_per_env: int = 128
    shaping_coef: float = 1.0
    save_interval: int = 100


@dataclass(frozen=True)
class FinetuneConfig:
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

    """

    lambda_kl: float = 2.5
    iterations: int = 1000
    num_envs: int = 1
    num_steps_per_env: int = 128
    num_learning_epochs: int = 16
    learning_rate: float = 2.5e-4
    anneal_lr: bool = False
    reinit_critic: bool = True
    env_reward_coef: float = 0.0
    save_interval: int = 100


@dataclass(frozen=True)
class FeedbackConfig:
    """Where beliefs come from and how they are fused.

    Attributes:
        source: Belief source kind: ``replay``, ``ollama`` or ``rules``.
        recording: Recording file replayed by the ``replay`` source.
        model: LLM name for the ``ollama`` source.
        host: Ollama server URL; empty: ``$OLLAMA_HOST``, else ``http://127.0.0.1:11434``.
        concurrency: Requests in flight at once.
        timeout_s: Seconds before one request is abandoned.
        miss_policy: What a replay miss gives: ``uniform``, ``fallback`` or ``error``.
        store: SQLite belief store (cache of every answer).
        clusters: Moral clusters of the panel.
        fusion: Fusion rule of the ``amuled`` variant.
        ollama: Further keyword arguments of
            :class:`~amuled_ma.beliefs.ollama.OllamaSource` (``num_predict``, ``num_ctx``,
            ``reasoning``, ``seed``, ``retries``, ...), checked against its signature.

    """

    source: str = "replay"
    recording: str = ""
    model: str = ""
    host: str = ""
    concurrency: int = 4
    timeout_s: float = 120.0
    miss_policy: str = "uniform"
    store: str = "beliefs.sqlite"
    clusters: list[str] = field(default_factory=lambda: list(PAPER_CLUSTERS))
    fusion: str = "bjs-dst"
    ollama: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class EvaluationConfig:
    """Evaluation protocol.

    Attributes:
        episodes: Episodes per policy and mode.
        seed: Seed of the evaluation episodes (distinct from training seeds).
        modes: ``greedy`` and/or ``sampled`` action selection.
        confidence: Confidence level of the reported intervals.

    """

    episodes: int = 50
    seed: int = 10_000
    modes: list[str] = field(default_factory=lambda: ["greedy", "sampled"])
    confidence: float = 0.95


@dataclass(frozen=True)
class OutputConfig:
    """Where runs go.

    Attributes:
        runs_dir: Folder holding one sub-folder per run.
        tensorboard: Write TensorBoard event files.

    """

    runs_dir: str = "runs"
    tensorboard: bool = True


@dataclass(frozen=True)
class Scenario:
    """A whole experiment setup.

    Attributes:
        name: Scenario name (the file stem unless ``name`` is set at top level).
        path: The file it was loaded from (None when built in code).
        task: See :class:`TaskConfig`.
        ppo: See :class:`PPOConfig`.
        base: See :class:`BaseConfig`.
        finetune: See :class:`FinetuneConfig`.
        feedback: See :class:`FeedbackConfig`.
        evaluation: See :class:`EvaluationConfig`.
        output: See :class:`OutputConfig`.

    """

    name: str = "scenario"
    path: Path | None = None
    task: TaskConfig = field(default_factory=TaskConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    base: BaseConfig = field(default_factory=BaseConfig)
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    @property
    def base_dir(self) -> Path:
        """Folder that relative paths of this scenario are resolved against."""
        return self.path.parent if self.path is not None else Path.cwd()

    def resolve(self, value: str) -> Path:
        """Resolve a path from this scenario against its folder."""
        path = Path(os.path.expandvars(os.path.expanduser(value)))
        return path if path.is_absolute() else (self.base_dir / path).resolve()

    def recording_path(self) -> Path:
        """Path of the replayed recording, with ``$AMULED_RECORDINGS`` as a fallback folder."""
        path = self.resolve(self.feedback.recording)
        if not path.exists() and os.environ.get("AMULED_RECORDINGS"):
            alt = Path(os.environ["AMULED_RECORDINGS"]) / Path(self.feedback.recording).name
            if alt.exists():
                return alt
        return path

    def to_dict(self) -> dict[str, Any]:
        """Return the fully resolved scenario as plain data (for ``config.json``)."""
        data = dataclasses.asdict(self)
        data["path"] = str(self.path) if self.path else None
        return data

    def replace(self, section: str, **changes: Any) -> Scenario:
        """Return a copy with some keys of one section changed (validated like a file)."""
        current = getattr(self, section)
        merged = {f.name: getattr(current, f.name) for f in dataclasses.fields(current)}
        for key, value in changes.items():
            merged[key] = value
        new_section = _build(type(current), merged, f"<override of [{section}]>", section)
        return dataclasses.replace(self, **{section: new_section})


_SECTIONS: dict[str, type] = {
    "task": TaskConfig,
    "ppo": PPOConfig,
    "base": BaseConfig,
    "finetune": FinetuneConfig,
    "feedback": FeedbackConfig,
    "evaluation": EvaluationConfig,
    "output": OutputConfig,
}

_CHOICES: dict[tuple[str, str], tuple[str, ...]] = {
    ("feedback", "source"): ("replay", "ollama", "rules"),
    ("feedback", "miss_policy"): ("uniform", "fallback", "error"),
    ("ppo", "activation"): ("tanh", "relu", "elu", "selu", "lrelu", "sigmoid", "identity"),
}

_POSITIVE: set[tuple[str, str]] = {
    ("base", "total_steps"),
    ("base", "num_envs"),
    ("base", "num_steps_per_env"),
    ("finetune", "iterations"),
    ("finetune", "num_envs"),
    ("finetune", "num_steps_per_env"),
    ("finetune", "num_learning_epochs"),
    ("ppo", "num_learning_epochs"),
    ("ppo", "num_mini_batches"),
    ("evaluation", "episodes"),
}


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is list:
        (inner,) = typing.get_args(tp)
        return f"list of {_type_name(inner)}"
    if origin is dict:
        return "table"
    if tp is float:
        return "float"
    if tp is int:
        return "integer"
    if tp is str:
        return "string"
    if tp is bool:
        return "boolean"
    return getattr(tp, "__name__", str(tp))


def _found_name(value: Any) -> str:
    return {
        bool: "boolean",
        int: "integer",
        float: "float",
        str: "string",
        list: "array",
        dict: "table",
    }.get(type(value), type(value).__name__)


def _check(tp: Any, value: Any) -> Any:
    """Return the value converted to ``tp`` or raise TypeError."""
    origin = typing.get_origin(tp)
    if origin is list:
        (inner,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise TypeError
        return [_check(inner, v) for v in value]
    if origin is dict:
        if not isinstance(value, dict):
            raise TypeError
        return dict(value)
    if isinstance(origin, type) and issubclass(origin, types.UnionType):  # pragma: no cover
        raise TypeError
    if tp is bool:
        if not isinstance(value, bool):
            raise TypeError
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise TypeError
        return value
    raise TypeError  # pragma: no cover


def _build(cls: type, table: dict[str, Any], source: str, section: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs: dict[str, Any] = {}
    for key, value in table.items():
        if key not in hints:
            raise ScenarioError(
                f"{source}: unknown key [{section}].{key}; expected one of: {', '.join(names)}"
            )
        try:
            kwargs[key] = _check(hints[key], value)
        except TypeError:
            raise ScenarioError(
                f"{source}: key [{section}].{key} expects {_type_name(hints[key])}, "
                f"found {_found_name(value)} ({value!r})"
            ) from None
        choices = _CHOICES.get((section, key))
        if choices and kwargs[key] not in choices:
            raise ScenarioError(
                f"{source}: key [{section}].{key} expects one of {', '.join(choices)}, "
                f"found {value!r}"
            )
        if (section, key) in _POSITIVE and kwargs[key] <= 0:
            raise ScenarioError(
                f"{source}: key [{section}].{key} expects a positive integer, found {value!r}"
            )
    for key in ("learning_rate", "gamma", "lam", "lambda_kl", "confidence"):
        if key in kwargs and kwargs[key] < 0:
            raise ScenarioError(
                f"{source}: key [{section}].{key} expects a non-negative float, "
                f"found {kwargs[key]!r}"
            )
    if section == "evaluation":
        for mode in kwargs.get("modes", []):
            if mode not in ("greedy", "sampled"):
                raise ScenarioError(
                    f"{source}: key [evaluation].modes expects greedy and/or sampled, "
                    f"found {mode!r}"
                )
    return cls(**kwargs)


def scenario_from_dict(data: dict[str, Any], *, path: Path | None = None) -> Scenario:
    """Build and validate a :class:`Scenario` from parsed TOML data.

    Args:
        data: The parsed TOML document.
        path: The file it came from (used in errors and to resolve relative paths).

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: Unknown section or key, or a value of the wrong type.

    """
    source = str(path) if path is not None else "<scenario>"
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key == "name":
            if not isinstance(value, str):
                raise ScenarioError(
                    f"{source}: key name expects string, found {_found_name(value)} ({value!r})"
                )
            kwargs["name"] = value
            continue
        if key not in _SECTIONS:
            raise ScenarioError(
                f"{source}: unknown section or key {key!r}; expected name or one of the tables "
                f"{', '.join(f'[{s}]' for s in _SECTIONS)}"
            )
        if not isinstance(value, dict):
            raise ScenarioError(
                f"{source}: key {key} expects table, found {_found_name(value)} ({value!r})"
            )
        kwargs[key] = _build(_SECTIONS[key], value, source, key)
    kwargs.setdefault("name", path.stem if path is not None else "scenario")
    return Scenario(path=path, **kwargs)


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
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{path}: not valid TOML: {error}") from None
    return scenario_from_dict(data, path=path)
