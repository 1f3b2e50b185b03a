"""Which training jobs train together as one population, and how many fit in memory.

A job is a :class:`MemberSpec` (its scenario, folder, variant, feedback, base). Jobs
train as one population (:class:`~amuled_ma.learn.population.PopulationTrainer`) when
their :func:`population_key` is equal: the same task (all of ``[task]`` but the seed), the
same network and PPO settings, the same run shape (copies, rollout, epochs, mini-batches,
iterations, learning rate and its schedule, reward weights) and, when resumed, the same
iteration (one Adam step counter and one runner serve them all). They may differ in seed,
feedback (source, clusters, fusion rule, recording), KL weight and recipe, base policy,
folders and checkpoint cadence.

:func:`split_populations` groups a list of jobs by that key and cuts each group into
populations whose estimated memory (:func:`member_memory_bytes` per member) fits a budget;
:func:`population_config` is rsl-rl's config of a population from its members' own.
"""

from __future__ import annotations

import copy
import itertools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from amuled_ma.learn.checkpoints import LAST, checkpoint_infos
from amuled_ma.learn.job_shape import JobShape, job_shape
from amuled_ma.scenario import Scenario
from amuled_ma.scenario.memory import MEMORY_FRACTION, physical_memory_bytes
from amuled_ma.variants import Variant

#: ``module:Class`` names rsl-rl resolves for a population.
POPULATION_MODEL = "amuled_ma.learn.population_models:PopulationMLPModel"
POPULATION_CATEGORICAL = "amuled_ma.learn.population_models:PopulationCategoricalDistribution"
POPULATION_PPO = "amuled_ma.learn.population_ppo:PopulationPPO"


#: A member's variant unless it says otherwise.
BASE_VARIANT = Variant("base")

#: Settings of a job's rsl-rl algorithm that may differ between members of a population.
MEMBER_ALGORITHM_KEYS = ("lambda_kl", "anchor")

#: Bytes of a float32.
FLOAT = 4

#: Bytes of one member beyond its tensors, measured on FindMilk with the authors' recipe
#: (``docs/learning.md``, "Population training"): its share of the population's Python
#: objects (about 0.3 MiB) and the growth of its feedback's memo and curves over the first
#: iterations (about 0.5 MiB); the memo keeps growing with the distinct states answered.
MEMBER_OVERHEAD_BYTES = 2**20

#: Bytes of one member's feedback object as built today: each job's replay source loads
#: its recording (3.4 MiB measured for ``findmilk-gpt-4o-mini``); the caller builds it.
FEEDBACK_BYTES = 4 * 2**20


@dataclass
class MemberSpec:
    """One training job, a member of a population (a job alone: a population of one).

    Attributes:
        scenario: The scenario.
        out_dir: The job's folder (its checkpoints, curve, config as a lone job's).
        variant: ``base``, ``shaped`` or ``finetune:<feedback>``.
        feedback: A fine-tune's feedback (its own; the belief store may be shared).
        base_checkpoint: A fine-tune's base policy.
        resume: Continue from ``out_dir/model_last.pt`` when present.
        seed: Overrides the scenario's seed.
        iterations: Overrides the number of iterations.
        resume_hint: The command that resumes this job (printed on Ctrl-C).
        on_iteration: Called as ``fn(member, iteration)`` after every iteration, with the
            member's :class:`~amuled_ma.learn.population.PopulationMember`.
        task_factory: Replaces :func:`~amuled_ma.tasks.make_task` (same signature).
        planned_shape: Its shape as its plan carries it (None: derived from the scenario).

    """

    scenario: Scenario
    out_dir: Path
    variant: Variant = BASE_VARIANT
    feedback: Any = None
    base_checkpoint: Path | None = None
    resume: bool = False
    seed: int | None = None
    iterations: int | None = None
    resume_hint: str | None = None
    on_iteration: Callable[[Any, int], None] | None = None
    task_factory: Callable[..., Any] | None = None
    planned_shape: JobShape | None = None

    def __post_init__(self) -> None:
        self.out_dir = Path(self.out_dir)

    @property
    def training_seed(self) -> int:
        """The seed the job trains with (``seed``, else ``[task].seed``)."""
        return self.scenario.task.seed if self.seed is None else int(self.seed)

    def shape(self) -> JobShape:
        """The job's shape: its plan's, else :func:`~amuled_ma.learn.job_shape.job_shape`."""
        if self.planned_shape is not None:
            return self.planned_shape
        sc = self.scenario
        return job_shape(
            sc.ppo,
            sc.base,
            sc.finetune,
            self.variant,
            self.iterations,
            where=str(sc.path or sc.name),
        )

    def start_iteration(self) -> int:
        """The iteration the job starts at: its checkpoint's when resumed, else 0."""
        if not self.resume:
            return 0
        infos = checkpoint_infos(self.out_dir / LAST)
        return int((infos or {}).get("iteration", 0))

    def lone_kwargs(self) -> dict[str, Any]:
        """The job as keyword arguments (of the lone loop ``tests/learn`` checks against)."""
        return {
            "variant": self.variant,
            "feedback": self.feedback,
            "base_checkpoint": self.base_checkpoint,
            "resume": self.resume,
            "seed": self.seed,
            "iterations": self.iterations,
            "resume_hint": self.resume_hint,
            "task_factory": self.task_factory,
        }


def shared_config(cfg: dict[str, Any]) -> dict[str, Any]:
    """An rsl-rl config without what may differ between members (KL weight, recipe, cadence)."""
    shared = json.loads(json.dumps(cfg))
    shared.pop("save_interval", None)
    for key in MEMBER_ALGORITHM_KEYS:
        shared["algorithm"].pop(key, None)
    return shared


def population_key(spec: MemberSpec) -> str:
    """What jobs of one population share (equal keys: they may train together).

    The task without its seed, the finetuning flag, the job's shape without the member
    settings (:func:`shared_config`), the learning-rate schedule, the start iteration and
    the task factory.
    """
    shape = spec.shape()
    task = spec.scenario.task.model_dump(mode="json")
    task.pop("seed", None)
    factory = spec.task_factory
    return json.dumps(
        {
            "task": task,
            "finetuning": shape.finetuning,
            "num_envs": shape.num_envs,
            "steps_per_env": shape.steps_per_env,
            "iterations": shape.total_iterations,
            "learning_rate": shape.learning_rate,
            "anneal": shape.anneal,
            "shaping_coef": shape.shaping_coef,
            "task_weight": shape.task_weight,
            "cfg": shared_config(shape.cfg),
            "start": spec.start_iteration(),
            "task_factory": None if factory is None else f"{factory.__module__}.{factory!r}",
        },
        sort_keys=True,
    )


def member_memory_bytes(
    shape: JobShape,
    *,
    obs_dim: int = 64,
    num_actions: int = 16,
    device: str = "cpu",
    feedback_bytes: int | None = None,
) -> int:
    """Estimated memory of one member of a population [bytes].

    Its tensors: actor and critic parameters with their gradients and Adam's two moments,
    the frozen base actor, its share of the rollout storage (observation, one-hot action,
    the distribution's log-probabilities, reward, done, value, log-probability, return,
    advantage per transition) and of a mini-batch's activations and gathered copies,
    the authors' window KL; plus, on the CPU, :data:`MEMBER_OVERHEAD_BYTES` (its Python
    objects, memo and curves) and its feedback object (:data:`FEEDBACK_BYTES` for a
    fine-tune). ``obs_dim`` and ``num_actions`` default to the generous bounds of
    :mod:`amuled_ma.scenario.memory`.

    Args:
        shape: The job's shape.
        obs_dim: Observation length.
        num_actions: Actions.
        device: Where the tensors live (``cuda``: the estimate is of the device's memory;
            the Python objects stay on the CPU).
        feedback_bytes: A fine-tune's feedback object (default :data:`FEEDBACK_BYTES`).

    """
    hidden = list(shape.cfg["actor"]["hidden_dims"])

    def parameters(outputs: int) -> int:
        sizes = [obs_dim, *hidden, outputs]
        return sum((a + 1) * b for a, b in itertools.pairwise(sizes))

    actor, critic = parameters(num_actions), parameters(1)
    weights = FLOAT * (4 * (actor + critic) + actor)
    transitions = shape.num_envs * shape.steps_per_env
    per_transition = obs_dim + 2 * num_actions + 7
    rollout = FLOAT * transitions * per_transition
    algorithm = shape.cfg["algorithm"]
    mini_batch = max(1, transitions // int(algorithm["num_mini_batches"]))
    activations = FLOAT * mini_batch * (2 * sum(hidden) * 3 + per_transition)
    window = 2 * 8 * transitions
    tensors = weights + rollout + activations + window
    if device.startswith("cuda"):
        return tensors
    if feedback_bytes is None:
        feedback_bytes = FEEDBACK_BYTES if shape.finetuning else 0
    return tensors + MEMBER_OVERHEAD_BYTES + feedback_bytes


def memory_budget_bytes() -> int:
    """The default budget of one population: half of this machine's physical memory."""
    return int(MEMORY_FRACTION * physical_memory_bytes())


def split_populations(
    specs: Sequence[MemberSpec],
    memory_budget: int | None = None,
    *,
    max_size: int | None = None,
    min_count: int = 1,
    device: str = "cpu",
) -> list[list[int]]:
    """Group jobs into populations: equal :func:`population_key`, within a memory budget.

    Args:
        specs: The jobs.
        memory_budget: Bytes one population may use (default: :func:`memory_budget_bytes`).
        max_size: At most this many members per population (None: no limit but memory).
        min_count: Cut each group into at least this many populations (as many as it
            has jobs at most): one per worker, so that ``min_count`` cores train at once
            (two populations of ``P/2`` do more than one of ``P`` on two cores).
        device: Where the populations train (the estimate's device).

    Returns:
        Populations as lists of indices into ``specs``, in the order of their first job;
        jobs keep their order inside a population. A job alone in its key is a
        population of one.

    Raises:
        ValueError: ``memory_budget`` or ``max_size`` is below 1.

    """
    budget = memory_budget_bytes() if memory_budget is None else int(memory_budget)
    if budget < 1 or (max_size is not None and max_size < 1) or min_count < 1:
        raise ValueError("memory_budget, max_size and min_count must be positive")
    groups: dict[str, list[int]] = {}
    for index, spec in enumerate(specs):
        groups.setdefault(population_key(spec), []).append(index)
    populations: list[list[int]] = []
    for members in groups.values():
        each = member_memory_bytes(specs[members[0]].shape(), device=device)
        size = max(1, budget // each)
        if max_size is not None:
            size = min(size, max_size)
        count = min(len(members), max(math.ceil(len(members) / size), min_count))
        # as even as the budget allows: 100 jobs at 32 a population are 4 of 25, not 32,32,32,4
        small, larger = divmod(len(members), count)
        start = 0
        for k in range(count):
            end = start + small + (1 if k < larger else 0)
            populations.append(members[start:end])
            start = end
    return populations


def population_config(cfgs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """rsl-rl's config of a population from its members' lone configs.

    The population's model, distribution and algorithm classes, the population size, and
    each member's KL weight and anchor as lists.

    Raises:
        ValueError: The members' configs differ in a setting they must share.

    """
    shared = shared_config(cfgs[0])
    for p, cfg in enumerate(cfgs):
        if shared_config(cfg) != shared:
            raise ValueError(f"member {p} has other training settings than member 0")
    cfg = copy.deepcopy(cfgs[0])
    size = len(cfgs)
    for model in ("actor", "critic"):
        cfg[model]["class_name"] = POPULATION_MODEL
        cfg[model]["population"] = size
    cfg["actor"]["distribution_cfg"]["class_name"] = POPULATION_CATEGORICAL
    algorithm = cfg["algorithm"]
    algorithm["class_name"] = POPULATION_PPO
    algorithm["population"] = size
    for key in MEMBER_ALGORITHM_KEYS:
        algorithm[key] = [member["algorithm"][key] for member in cfgs]
    return cfg
