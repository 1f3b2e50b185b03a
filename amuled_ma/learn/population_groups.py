"""Which training jobs train together as one population (equal `population_key`), how many fit."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from amuled_ma.learn.checkpoints import LAST, checkpoint_infos
from amuled_ma.learn.job_shape import JobShape, job_shape
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import Scenario
from amuled_ma.scenario.memory import MEMORY_FRACTION, physical_memory_bytes

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

#: Bytes of one member's feedback object: its replay source loads its recording (3.4 MiB
#: measured for ``findmilk-gpt-4o-mini``).
FEEDBACK_BYTES = 4 * 2**20


@dataclass
class MemberSpec:
    """One training job, a member of a population (a job alone: a population of one).

    ``variant`` is ``base``, ``shaped`` or ``finetune:<feedback>``; ``on_iteration`` is
    called as ``fn(member, iteration)``; ``task_factory`` replaces `make_task`;
    ``planned_shape`` None derives the shape from the scenario.
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
        """The job's shape: its plan's, else `job_shape`."""
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


def population_key(spec: MemberSpec) -> str:
    """What jobs of one population share: task without seed, shape, schedule, start, factory."""
    shape, factory = spec.shape(), spec.task_factory
    shared = json.loads(json.dumps(shape.cfg))  # without what members may differ in
    shared.pop("save_interval", None)
    for name in MEMBER_ALGORITHM_KEYS:
        shared["algorithm"].pop(name, None)
    key = dataclasses.asdict(shape) | {
        "task": spec.scenario.task.model_dump(mode="json", exclude={"seed"}),
        "cfg": shared,
        "start": spec.start_iteration(),
        "task_factory": None if factory is None else f"{factory.__module__}.{factory!r}",
    }
    return json.dumps(key, sort_keys=True)


def member_memory_bytes(
    shape: JobShape,
    *,
    obs_dim: int = 64,
    num_actions: int = 16,
    device: str = "cpu",
    feedback_bytes: int | None = None,
) -> int:
    """Estimated memory of one member of a population [bytes].

    Its tensors (networks, gradients, Adam moments, base actor, its share of the rollout
    storage and mini-batches, window KL) plus, on the CPU, `MEMBER_OVERHEAD_BYTES` and its
    feedback (``feedback_bytes``, default `FEEDBACK_BYTES` for a fine-tune). ``obs_dim`` and
    ``num_actions`` default to the bounds of `amuled_ma.scenario.memory`.
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
    """Indices into ``specs`` grouped by `population_key` within ``memory_budget`` bytes.

    ``min_count`` (at least 1) cuts each group into at least that many populations (one per
    worker).
    """
    budget = memory_budget_bytes() if memory_budget is None else int(memory_budget)
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
        populations += [part.tolist() for part in np.array_split(np.array(members), count)]
    return populations


def population_config(cfgs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """rsl-rl's config of a population from its members' lone configs (KL weights as lists).

    The members share a `population_key` (checked by `PopulationTrainer`).
    """
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
