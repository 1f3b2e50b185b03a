"""Scenarios: everything one experiment needs, read from a TOML file and validated.

A scenario file has one table per concern (``[task]``, ``[ppo]``, ``[base]``,
``[finetune]``, ``[feedback]``, ``[evaluation]``, ``[output]``); each maps onto a
frozen dataclass below. Every key is checked on load: an unknown key or a value of
the wrong type raises :class:`~amuled_ma.errors.ScenarioError` naming the file, the
key, the expected type and the type found. Keys left out take the defaults below,
which follow the paper (Dubey, Dailisan, Mahajan, "AMULED") and CleanRL's PPO.

Every number has a range, declared next to its field (``metadata={"range": Range(...)}``)
and enforced by one checker, :func:`validate_section`, on load, on ``--set`` overrides
(:meth:`Scenario.replace`) and on construction in code (``__post_init__``): NaN and
infinities are always refused, and so are sizes whose buffers would not fit in
:data:`MEMORY_FRACTION` of the machine's memory and runs longer than
:data:`MAX_ENV_STEPS`. Values used as folder names (the scenario ``name``,
``[task].name``) must be one safe path component (:func:`check_path_component`);
:func:`safe_child` builds a path below a root and refuses one that would leave it.

Relative paths in a scenario (recordings, belief store, output folder) are resolved
against the scenario file's folder, never the current directory. A shipped scenario
can be named without a path (``amuled run findmilk``): see :func:`resolve_scenario_path`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import tomllib
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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


@dataclass(frozen=True)
class Range:
    """The allowed values of a numeric scenario key; NaN and infinities never are.

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


def _range(
    low: float | None = None,
    high: float | None = None,
    *,
    why: str,
    low_open: bool = False,
    high_open: bool = False,
    length: Range | None = None,
) -> dict[str, Any]:
    """Field metadata declaring a key's range (and a list's length range)."""
    meta: dict[str, Any] = {"range": Range(low, high, low_open, high_open, why)}
    if length is not None:
        meta["length"] = length
    return meta


#: Field metadata of a string used as a folder or file name.
_COMPONENT: dict[str, Any] = {"component": True}

_SEED = _range(0, MAX_SEED, why="a seed of torch and of the tasks' 64-bit random streams")
_EPOCHS = _range(1, 1000, why="optimisation passes over each rollout; CleanRL 4, authors 16")
_LR = _range(
    0, 1, low_open=True, why="Adam step size: 0 learns nothing, beyond 1 the update diverges"
)
_SAVE = _range(1, why="iterations between checkpoints; 0 would divide by zero")
_ENVS = _range(1, why="parallel copies; with num_steps_per_env also checked against memory")
_STEPS_PER_ENV = _range(1, why="rollout length per copy; with num_envs also checked against memory")
_NONNEG = "a weight; negative flips the term's sign"


class _Validated:
    """Mixin: a section checks its numbers and names whenever it is built (also in code)."""

    def __post_init__(self) -> None:
        section = _SECTION_OF.get(type(self))
        if section is not None:
            fields = dataclasses.fields(typing.cast(Any, self))
            values = {f.name: getattr(self, f.name) for f in fields}
            validate_section(section, values, "<scenario built in code>")


@dataclass(frozen=True)
class TaskConfig(_Validated):
    """The task environment.

    Attributes:
        name: Task name known to :func:`amuled_ma.tasks.get_task` (``findmilk``, ``driving``);
            also a file name (prompt templates), so one safe path component.
        seed: Base random seed of the run.
        max_steps: Episode step limit; 0 keeps the task's own default.
        options: Extra keyword options passed to the task constructor.

    """

    name: str = field(default="findmilk", metadata=_COMPONENT)
    seed: int = field(default=1, metadata=_SEED)
    max_steps: int = field(
        default=0,
        metadata=_range(0, 10**7, why="episode step limit; 0 keeps the task's default"),
    )
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PPOConfig(_Validated):
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

    hidden_dims: list[int] = field(
        default_factory=lambda: [64, 64],
        metadata=_range(
            1,
            65_536,
            why="units of a hidden layer; the networks are also checked against memory",
            length=Range(1, 64, why="rsl-rl's MLP needs at least one hidden layer"),
        ),
    )
    activation: str = "tanh"
    learning_rate: float = field(default=2.5e-4, metadata=_LR)
    anneal_lr: bool = True
    gamma: float = field(
        default=0.99,
        metadata=_range(0, 1, why="discount factor: above 1 returns grow without bound"),
    )
    lam: float = field(
        default=0.95,
        metadata=_range(0, 1, why="GAE lambda, a weight between TD(0) and Monte Carlo"),
    )
    clip_param: float = field(
        default=0.2,
        metadata=_range(
            0,
            1,
            low_open=True,
            high_open=True,
            why="PPO ratio clip: the ratio is clipped to [1 - clip, 1 + clip], which must be "
            "positive",
        ),
    )
    entropy_coef: float = field(default=0.01, metadata=_range(0, why=_NONNEG))
    value_loss_coef: float = field(default=0.5, metadata=_range(0, why=_NONNEG))
    max_grad_norm: float = field(
        default=0.5,
        metadata=_range(0, low_open=True, why="gradient norm clip: 0 would zero every update"),
    )
    num_learning_epochs: int = field(default=4, metadata=_EPOCHS)
    num_mini_batches: int = field(
        default=4,
        metadata=_range(1, 65_536, why="mini-batches per epoch; each needs transitions"),
    )
    normalize_advantage_per_mini_batch: bool = True


@dataclass(frozen=True)
class BaseConfig(_Validated):
    """Base training (paper, Simulation Studies): ``r = r_env + c * r_shaping``.

    Attributes:
        total_steps: Environment steps of the whole run (all copies together).
        num_envs: Parallel environment copies.
        num_steps_per_env: Rollout length per copy and iteration.
        shaping_coef: ``c`` of the ``shaped`` variant (the ``base`` variant uses 0).
        save_interval: Iterations between checkpoints.

    """

    total_steps: int = field(
        default=500_000,
        metadata=_range(
            1,
            MAX_ENV_STEPS,
            why="env steps of the run, capped at MAX_ENV_STEPS (about 28 h at 100k steps/s)",
        ),
    )
    num_envs: int = field(default=4, metadata=_ENVS)
    num_steps_per_env: int = field(default=128, metadata=_STEPS_PER_ENV)
    shaping_coef: float = field(
        default=1.0,
        metadata=_range(0, why="weight c of the shaping reward (the tasks need c >= 0)"),
    )
    save_interval: int = field(default=100, metadata=_SAVE)


@dataclass(frozen=True)
class FinetuneConfig(_Validated):
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

    lambda_kl: float = field(
        default=2.5,
        metadata=_range(
            0, why="weight of the KL anchor to the base policy; negative rewards drifting away"
        ),
    )
    iterations: int = field(
        default=1000,
        metadata=_range(
            1, 10**8, why="PPO iterations; iterations x num_envs x num_steps_per_env is also capped"
        ),
    )
    num_envs: int = field(default=1, metadata=_ENVS)
    num_steps_per_env: int = field(default=128, metadata=_STEPS_PER_ENV)
    num_learning_epochs: int = field(default=16, metadata=_EPOCHS)
    learning_rate: float = field(default=2.5e-4, metadata=_LR)
    anneal_lr: bool = False
    reinit_critic: bool = True
    env_reward_coef: float = field(default=0.0, metadata=_range(0, why=_NONNEG))
    save_interval: int = field(default=100, metadata=_SAVE)
    recipe: str = "equation"


@dataclass(frozen=True)
class FeedbackConfig(_Validated):
    """Where beliefs come from and how they are fused.

    Attributes:
        source: Belief source kind: ``replay``, ``ollama`` or ``rules``.
        recording: Recording file replayed by the ``replay`` source.
        model: LLM name for the ``ollama`` source.
        host: Ollama server URL; empty: ``$OLLAMA_HOST``, else ``http://127.0.0.1:11434``.
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
        fusion: Fusion rule of the ``amuled`` variant.
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

    """

    source: str = "replay"
    recording: str = ""
    model: str = ""
    host: str = ""
    concurrency: int = field(
        default=4, metadata=_range(1, 1024, why="LLM requests in flight, one connection each")
    )
    timeout_s: float = field(
        default=120.0,
        metadata=_range(
            0, 86_400, low_open=True, why="seconds per LLM request: 0 fails all, above a day hangs"
        ),
    )
    miss_policy: str = "uniform"
    cluster_recording: str = ""
    store: str = "beliefs.sqlite"
    clusters: list[str] = field(default_factory=lambda: list(PAPER_CLUSTERS))
    fusion: str = "bjs-dst"
    ollama: dict[str, Any] = field(default_factory=dict)
    agents: dict[str, dict[str, Any]] = field(default_factory=dict)
    clusters_dirs: list[str] = field(default_factory=list)
    max_abstention: float = field(
        default=0.2,
        metadata=_range(
            0, 1, why="share of rewarded steps an agent may leave unanswered before a run stops"
        ),
    )
    name: str = ""


@dataclass(frozen=True)
class EvaluationConfig(_Validated):
    """Evaluation protocol.

    Attributes:
        episodes: Episodes per policy and mode.
        seed: Seed of the evaluation episodes (distinct from training seeds).
        modes: ``greedy`` and/or ``sampled`` action selection.
        confidence: Confidence level of the reported intervals.

    """

    episodes: int = field(
        default=50,
        metadata=_range(
            1,
            1_000_000,
            why="episodes run as parallel task copies (paper: 50); also checked against memory",
        ),
    )
    seed: int = field(default=10_000, metadata=_SEED)
    modes: list[str] = field(default_factory=lambda: ["greedy", "sampled"])
    confidence: float = field(
        default=0.95,
        metadata=_range(
            0,
            1,
            low_open=True,
            high_open=True,
            why="two-sided confidence level; 1 would need an infinite interval",
        ),
    )


@dataclass(frozen=True)
class OutputConfig(_Validated):
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
        """Return the fully resolved scenario as plain data (for ``config.json``)."""
        data = dataclasses.asdict(self)
        data["path"] = str(self.path) if self.path else None
        return data

    def __post_init__(self) -> None:
        check_path_component(self.name, f"{self.path or '<scenario>'}: key name")

    def replace(self, section: str, **changes: Any) -> Scenario:
        """Return a copy with some keys of one section changed (validated like a file)."""
        current = getattr(self, section)
        merged = {f.name: getattr(current, f.name) for f in dataclasses.fields(current)}
        for key, value in changes.items():
            merged[key] = value
        source = f"{self.path or self.name} (override of [{section}])"
        new_section = _build(type(current), merged, source, section)
        return dataclasses.replace(self, **{section: new_section})

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


_SECTIONS: dict[str, type] = {
    "task": TaskConfig,
    "ppo": PPOConfig,
    "base": BaseConfig,
    "finetune": FinetuneConfig,
    "feedback": FeedbackConfig,
    "evaluation": EvaluationConfig,
    "output": OutputConfig,
}

_SECTION_OF: dict[type, str] = {cls: name for name, cls in _SECTIONS.items()}

_CHOICES: dict[tuple[str, str], tuple[str, ...]] = {
    ("feedback", "source"): ("replay", "ollama", "rules"),
    ("feedback", "miss_policy"): ("uniform", "fallback", "error", "zero"),
    ("finetune", "recipe"): ("equation", "authors"),
    ("ppo", "activation"): ("tanh", "relu", "elu", "selu", "lrelu", "sigmoid", "identity"),
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


def _kind(value: Any, rng: Range) -> str:
    if isinstance(value, int) and not isinstance(value, bool):
        if rng.low is not None and rng.low >= 1:
            return "a positive integer"
        if rng.low == 0:
            return "a non-negative integer"
        return "an integer"
    return "a finite number"


def _check_number(key: str, value: Any, rng: Range, source: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ScenarioError(
            f"{source}: key {key} expects a number {rng.describe()}, "
            f"found {_found_name(value)} ({value!r})"
        )
    if value not in rng:
        raise ScenarioError(
            f"{source}: key {key} expects {_kind(value, rng)} {rng.describe()} "
            f"({rng.why}), found {value!r}"
        )


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


def validate_section(section: str, values: dict[str, Any], source: str) -> None:
    """Check every value of one section against its declared range and rules.

    Each numeric field's range is its ``metadata["range"]`` (a list's length range is
    ``metadata["length"]``); a field with ``metadata["component"]`` must be a safe path
    component; floats anywhere (also inside free-form tables) must be finite; sizes are
    checked against memory and the run length against :data:`MAX_ENV_STEPS`.

    Args:
        section: Section name (``ppo``).
        values: Every field of the section, by name.
        source: The file (or ``--set`` override) the values came from, for errors.

    Raises:
        ScenarioError: A value is out of range; the message names the file, the
            ``[section].key``, the expected range and why, and the value found.

    """
    for f in dataclasses.fields(_SECTIONS[section]):
        key, value = f"[{section}].{f.name}", values[f.name]
        if f.metadata.get("component"):
            check_path_component(value, f"{source}: key {key}")
        rng: Range | None = f.metadata.get("range")
        if rng is None:
            _check_finite(key, value, source)
        elif isinstance(value, list):
            length: Range | None = f.metadata.get("length")
            if length is not None and len(value) not in length:
                raise ScenarioError(
                    f"{source}: key {key} expects a list whose length is "
                    f"{length.describe()} ({length.why}), found {len(value)} entries ({value!r})"
                )
            for i, item in enumerate(value):
                _check_number(f"{key}[{i}]", item, rng, source)
        else:
            _check_number(key, value, rng, source)
    if section == "feedback" and values.get("agents") is not None:
        from amuled_ma.beliefs.routing import check_agent_tables

        check_agent_tables(
            values["agents"],
            where=source,
            clusters=values["clusters"],
            default_source=values["source"],
            default_model=values["model"],
        )
    if section == "feedback" and values.get("host"):
        from amuled_ma.beliefs.hosts import normalize_host

        normalize_host(values["host"], where=f"{source}: key [feedback].host")
    _check_budget(section, values, source)


# ------------------------------------------------------------------------------ types
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


def _float_for_int_hint(tp: Any, value: Any) -> str:
    """Explain a float written where an integer is expected (TOML reads ``1e8`` as float)."""
    wants_int = tp is int or (typing.get_origin(tp) is list and typing.get_args(tp) == (int,))
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


def _defaults(cls: type) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        else:
            out[f.name] = f.default_factory()  # type: ignore[misc]
    return out


def _build(cls: type, table: dict[str, Any], source: str, section: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs: dict[str, Any] = {}
    for key, value in table.items():
        if key not in names:
            raise ScenarioError(
                f"{source}: unknown key [{section}].{key}; expected one of: {', '.join(names)}"
            )
        try:
            kwargs[key] = _check(hints[key], value)
        except TypeError:
            raise ScenarioError(
                f"{source}: key [{section}].{key} expects {_type_name(hints[key])}, "
                f"found {_found_name(value)} ({value!r}){_float_for_int_hint(hints[key], value)}"
            ) from None
        choices = _CHOICES.get((section, key))
        if choices and kwargs[key] not in choices:
            raise ScenarioError(
                f"{source}: key [{section}].{key} expects one of {', '.join(choices)}, "
                f"found {value!r}"
            )
    if section == "evaluation":
        for mode in kwargs.get("modes", []):
            if mode not in ("greedy", "sampled"):
                raise ScenarioError(
                    f"{source}: key [evaluation].modes expects greedy and/or sampled, "
                    f"found {mode!r}"
                )
    validate_section(section, {**_defaults(cls), **kwargs}, source)
    return cls(**kwargs)


def scenario_from_dict(data: dict[str, Any], *, path: Path | None = None) -> Scenario:
    """Build and validate a :class:`Scenario` from parsed TOML data.

    Args:
        data: The parsed TOML document.
        path: The file it came from (used in errors and to resolve relative paths).

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: Unknown section or key, a value of the wrong type or out of its
            range (see :func:`validate_section`), or a name that is no safe folder name.

    """
    source = str(path) if path is not None else "<scenario>"
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key == "name":
            kwargs["name"] = check_path_component(value, f"{source}: key name")
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
    if "name" not in kwargs:
        stem = path.stem if path is not None else "scenario"
        kwargs["name"] = check_path_component(
            stem, f"{source}: the scenario name (the file name, as no top-level name is set)"
        )
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
        data = tomllib.loads(read_text(path, "scenario", ScenarioError))
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{path}: not valid TOML: {error}") from None
    return scenario_from_dict(data, path=path)
