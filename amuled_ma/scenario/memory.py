"""Size checks of a scenario: memory estimates of its buffers, the run-length cap, finite values."""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable, Iterator
from typing import Any

from amuled_ma.errors import ScenarioError

#: 500,000 and about 28 hours at 100,000 steps/s: a larger value is a typo, not a run.
MAX_ENV_STEPS = 10**10

#: Share of the machine's physical memory the estimated buffers of one section may fill.
MEMORY_FRACTION = 0.5

#: Estimated bytes of one stored rollout transition: the observation (up to
#: `ASSUMED_OBS_DIM` floats), PPO's per-step buffers (action, reward, done, value,
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


def leaves(key: str, value: object) -> Iterator[tuple[str, object]]:
    """Every value inside tables and arrays of ``value``, with its key (``options.a[0]``)."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from leaves(f"{key}.{k}", v)
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            yield from leaves(f"{key}[{i}]", v)
    else:
        yield key, value


def check_finite(key: str, value: object, source: str) -> None:
    """Refuse NaN and infinities anywhere in a free-form value (``options``, ``ollama``)."""
    for where, leaf in leaves(key, value):
        if isinstance(leaf, float) and not math.isfinite(leaf):
            raise ScenarioError(f"{source}: key {where} expects a finite number, found {leaf!r}")


def check_memory(
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


def check_budget(section: str, values: dict[str, Any], source: str) -> None:
    """Checks across keys of one section: memory estimates and the run-length cap."""
    if section in ("base", "finetune"):
        envs, steps = values["num_envs"], values["num_steps_per_env"]
        check_memory(
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
        its = values["iterations"]
        total = its * envs * steps
        if total > MAX_ENV_STEPS:
            raise ScenarioError(
                f"{source}: key [finetune].iterations x num_envs x num_steps_per_env = "
                f"{its:,} x {envs:,} x {steps:,} = {total:,} env steps; expected at most "
                f"MAX_ENV_STEPS = {MAX_ENV_STEPS:,} env steps (the cap on one run, about "
                f"28 hours at 100,000 steps/s), found iterations = {its!r}"
            )
    if section == "ppo":
        dims = [ASSUMED_OBS_DIM, *values["hidden_dims"], ASSUMED_NUM_ACTIONS]
        check_memory(
            f"[ppo].hidden_dims = {values['hidden_dims']!r} (actor and critic, "
            f"{ASSUMED_OBS_DIM} inputs, {ASSUMED_NUM_ACTIONS} outputs assumed)",
            sum(a * b + b for a, b in itertools.pairwise(dims)),
            BYTES_PER_PARAMETER,
            "network parameters",
            source,
            lambda _: " (use narrower or fewer hidden layers)",
        )
    if section == "evaluation":
        check_memory(
            "[evaluation].episodes",
            values["episodes"],
            BYTES_PER_EPISODE,
            "evaluation episodes",
            source,
            lambda _: f", found {values['episodes']!r}",
        )


#: Bytes of one parameter of the distilled model while it is fitted: float32 x (weight,
#: gradient, Adam's two moments).
BYTES_PER_DISTILL_PARAMETER = 16
#: Bytes of one activation of a fit, per hidden unit or output of a state: float32 x
#: (the forward value kept for the backward pass, its gradient, a temporary).
BYTES_PER_DISTILL_ACTIVATION = 12
#: Asked states a fit is assumed to hold when the budget is a share (of states not yet
#: visited): the fits are full-batch on every asked state; a count budget is its count.
ASSUMED_DISTILL_STATES = 4096


def distill_bytes(ensemble: int, hidden: int, members: int, budget: float | int) -> int:
    """Memory one fit of the distilled model takes [bytes], estimated."""
    outputs = members * ASSUMED_NUM_ACTIONS
    per_network = ASSUMED_OBS_DIM * hidden + hidden + hidden * hidden + hidden
    per_network += hidden * outputs + outputs
    states = budget if isinstance(budget, int) else ASSUMED_DISTILL_STATES
    parameters = ensemble * per_network * BYTES_PER_DISTILL_PARAMETER
    return parameters + ensemble * states * (2 * hidden + outputs) * BYTES_PER_DISTILL_ACTIVATION


def check_distill_memory(
    ensemble: int, hidden: int, members: int, budget: float | int, source: str
) -> None:
    """Refuse a distilled model whose `distill_bytes` exceed `MEMORY_FRACTION` of the memory."""
    memory = physical_memory_bytes()
    allowed = MEMORY_FRACTION * memory
    need = distill_bytes(ensemble, hidden, members, budget)
    if need <= allowed:
        return
    fits = next(
        (
            h
            for h in (2048, 1024, 512, 256, 128, 64)
            if distill_bytes(ensemble, h, members, budget) <= allowed
        ),
        None,
    )
    hint = f"e.g. hidden = {fits} at this ensemble" if fits else "a smaller ensemble or budget"
    states = budget if isinstance(budget, int) else ASSUMED_DISTILL_STATES
    raise ScenarioError(
        f"{source}: keys [feedback.distill].ensemble x hidden = {ensemble:,} x {hidden:,} "
        f"({members} members, {states:,} states a fit) need about {_bytes(need)} to fit the "
        f"distilled model, but at most {MEMORY_FRACTION:.0%} of this machine's "
        f"{_bytes(memory)} of memory may be used; {hint} (docs/distill.md)"
    )


#: Memory one planned training job holds before it runs [bytes, estimated]: its scenario,
#: record, panel plan and the scheduler's entry, with a safety factor.
BYTES_PER_PLANNED_JOB = 65_536
#: Most training replicas of one variant (``--seeds``): a sweep of more is a typo.
MAX_SEEDS = 10_000


def check_seed_replicas(seeds: int, variants: int, source: str = "the command line") -> None:
    """Refuse ``--seeds`` beyond `MAX_SEEDS` or planned jobs beyond the memory, before planning.

    Raises:
        ScenarioError: More than `MAX_SEEDS`, or ``seeds x variants`` jobs of
            `BYTES_PER_PLANNED_JOB` beyond `MEMORY_FRACTION` of the memory.
    """
    if seeds > MAX_SEEDS:
        raise ScenarioError(
            f"{source}: --seeds {seeds:,}: expected at most {MAX_SEEDS:,} training replicas "
            f"of each variant ({seeds:,} x {variants} variants would be "
            f"{seeds * variants:,} training jobs); give fewer seeds"
        )
    check_memory(
        f"--seeds x variants = {seeds:,} x {variants}",
        seeds * variants,
        BYTES_PER_PLANNED_JOB,
        "planned training jobs",
        source,
        lambda limit: f" (--seeds <= {max(limit // max(variants, 1), 1):,})",
    )
