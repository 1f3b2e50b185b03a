"""A population's training state, to and from its members' lone states (a lone job's format).

Per-copy tensors are concatenated member after member; tables shared by all copies are kept
once; Adam's step counter is shared.
"""

from __future__ import annotations

import contextlib
import copy
import io
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

from rsl_rl.runners import OnPolicyRunner

from amuled_ma.deliberation.mdp import BatchedDeliberation, FeedbackFn
from amuled_ma.errors import CheckpointError
from amuled_ma.learn.anchored_ppo import AnchoredPPO
from amuled_ma.learn.checkpoints import LAST, TRAINER_KEYS, read_checkpoint
from amuled_ma.learn.population_groups import MemberSpec
from amuled_ma.learn.vecenv import DeliberationVecEnv
from amuled_ma.tasks import make_task

_T = TypeVar("_T")


def quiet(fn: Callable[[], _T]) -> _T:
    """Call ``fn`` with its prints to stdout dropped (rsl-rl's runner prints when built)."""
    with contextlib.redirect_stdout(io.StringIO()):
        return fn()


@dataclass
class MemberStart:
    """Where a member starts: its lone job's state once built (`lone_start`).

    ``torch_rng``: torch's global random state after construction; ``env_state`` None: unsaved.
    """

    actor: dict[str, torch.Tensor]
    critic: dict[str, torch.Tensor]
    optimizer: dict[str, Any]
    base_actor: dict[str, torch.Tensor] | None
    iteration: int
    torch_rng: torch.Tensor
    env_state: dict[str, Any] | None
    curve: list[dict]
    wall_s: float
    obs_dim: int
    num_actions: int


def lone_start(spec: MemberSpec) -> tuple[MemberStart, OnPolicyRunner, DeliberationVecEnv]:
    """The member's start, lone runner (not yet anchored) and env, as its job builds them alone.

    Seeded, then a resumed job loads its ``model_last.pt`` and a new fine-tune its base.

    Raises:
        ValueError: A fine-tune without feedback.
        CheckpointError: The base checkpoint is missing, or a checkpoint does not fit.
    """
    torch.set_num_threads(1)
    scenario, shape = spec.scenario, spec.shape()
    base_checkpoint = Path(spec.base_checkpoint) if spec.base_checkpoint else None
    if shape.finetuning:
        if spec.feedback is None:
            raise ValueError("a fine-tune needs feedback")
        if base_checkpoint is None or not base_checkpoint.is_file():
            raise CheckpointError(f"base checkpoint not found: {base_checkpoint}")
    seed = spec.training_seed
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    cfg = {"scenario": scenario.name, "variant": str(spec.variant)}
    env = member_env(spec, shape.num_envs, spec.feedback, cfg)
    # rsl-rl mutates the dict it is given: hand it a copy
    runner = quiet(
        lambda: OnPolicyRunner(env, copy.deepcopy(shape.cfg), log_dir=None, device="cpu")
    )
    alg: AnchoredPPO = runner.alg
    iteration, curve, wall_s = 0, [], 0.0
    last = spec.out_dir / LAST
    if spec.resume and last.is_file():
        state = _load(alg, last, None, "checkpoint")
        iteration = int(state["iter"])
        infos = state.get("infos") or {}
        curve = list(infos.get("curve", []))
        wall_s = float(infos.get("wall_s", 0.0))
        if "torch_rng" in infos:
            torch.set_rng_state(infos["torch_rng"])
        if infos.get("env_state") is not None:  # the episodes it stopped in (else: reset)
            try:
                env.load_state_dict(infos["env_state"])
            except ValueError as error:
                raise CheckpointError(
                    f"{last}: {error}; it was saved by another task or number of copies "
                    "(retrain with --force)"
                ) from error
    elif shape.finetuning:
        assert base_checkpoint is not None
        load_cfg = {"actor": True, "critic": not scenario.finetune.reinit_critic}
        _load(alg, base_checkpoint, load_cfg, "base checkpoint")
    base_actor = None
    if shape.finetuning:
        assert base_checkpoint is not None
        base_actor = read_checkpoint(base_checkpoint)["actor_state_dict"]
    runner.current_learning_iteration = iteration
    saved = alg.save()
    start = MemberStart(
        actor=saved["actor_state_dict"],
        critic=saved["critic_state_dict"],
        optimizer=saved["optimizer_state_dict"],
        base_actor=base_actor,
        iteration=iteration,
        torch_rng=torch.get_rng_state(),
        env_state=env.state_dict(),
        curve=curve,
        wall_s=wall_s,
        obs_dim=int(env.obs.shape[-1]),
        num_actions=int(env.num_actions),
    )
    return start, runner, env


def member_env(
    spec: MemberSpec, copies: int, feedback: FeedbackFn | None, cfg: dict[str, Any]
) -> DeliberationVecEnv:
    """The learner's env of ``copies`` copies of ``spec``'s task (its seed), with ``feedback``."""
    shape = spec.shape()
    task = (spec.task_factory or make_task)(
        spec.scenario.task, copies, shaping_coef=shape.shaping_coef, seed=spec.training_seed
    )
    mdp = BatchedDeliberation(task, feedback, task_weight=shape.task_weight, feedback_coef=1.0)
    return DeliberationVecEnv(mdp, cfg=cfg)


def _load(alg: AnchoredPPO, path: Path, load_cfg: dict | None, what: str) -> dict:
    """Load a checkpoint read weights-only into rsl-rl's PPO through its public ``load``."""
    state = read_checkpoint(path, need=TRAINER_KEYS)
    try:
        alg.load(state, load_cfg, True)
    except (RuntimeError, KeyError, ValueError) as error:
        raise CheckpointError(
            f"cannot load {what} {path} into the scenario's networks ({error}); was it "
            "trained with other [ppo] hidden dims or another task? Retrain it with --force"
        ) from error
    return state


def stack_optimizer_states(states: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One optimiser's state dict over stacked parameters from the members' (member 0's groups).

    Adam's step is member 0's: the members start at one iteration (their `population_key`).
    """
    first = states[0]
    stacked: dict[Any, dict[str, Any]] = {}
    for index, entry in first["state"].items():
        stacked[index] = {
            name: value
            if name == "step"
            else torch.stack([state["state"][index][name] for state in states])
            for name, value in entry.items()
        }
    return {"state": stacked, "param_groups": first["param_groups"]}


def member_optimizer_state(state: Mapping[str, Any], member: int | None) -> dict[str, Any]:
    """Member ``member``'s lone optimiser state dict from the population's (on the CPU).

    ``member`` None: the state is a lone optimiser's already; a copy of it.
    """
    out: dict[Any, dict[str, Any]] = {}
    for index, entry in state["state"].items():
        out[index] = {
            name: (
                value.cpu().clone()
                if name == "step" or member is None
                else value[member].cpu().clone()
            )
            for name, value in entry.items()
        }
    return {"state": out, "param_groups": [dict(g) for g in state["param_groups"]]}


def stack_env_states(
    states: Sequence[Mapping[str, Any]], population_state: Mapping[str, Any]
) -> dict[str, Any]:
    """The population env's state from its members' lone env states (``population_state``: shapes).

    Raises:
        ValueError: A tensor is neither per copy nor shared, or a shared table differs
            between members.
    """
    members = len(states)
    out: dict[str, Any] = {}
    for key, mine in population_state.items():
        values = [state[key] for state in states]
        if isinstance(mine, Mapping):
            out[key] = stack_env_states(values, mine)
            continue
        if not torch.is_tensor(mine):
            out[key] = values[0]
            continue
        first = values[0]
        if tuple(first.shape) == tuple(mine.shape):
            for p, value in enumerate(values):
                if not torch.equal(value, first):
                    raise ValueError(f"env state {key!r}: member {p}'s differs from member 0's")
            out[key] = first.clone()
        elif mine.dim() and first.dim() and mine.shape[0] == members * first.shape[0]:
            out[key] = torch.cat(values)
        else:
            raise ValueError(
                f"env state {key!r}: a member's shape {tuple(first.shape)} does not stack "
                f"into the population's {tuple(mine.shape)}"
            )
    return out


def member_env_state(
    state: Mapping[str, Any], template: Mapping[str, Any], member: int
) -> dict[str, Any]:
    """Member ``member``'s lone env state from the population's (``template``: lone shapes)."""
    out: dict[str, Any] = {}
    for key, value in state.items():
        like = template[key]
        if isinstance(value, Mapping):
            out[key] = member_env_state(value, like, member)
        elif not torch.is_tensor(value) or tuple(value.shape) == tuple(like.shape):
            out[key] = value.clone() if torch.is_tensor(value) else value
        else:
            rows = like.shape[0]
            out[key] = value[member * rows : (member + 1) * rows].clone()
    return out


def split_episodes(episodes: Sequence[dict], population: int, copies: int) -> list[list[dict]]:
    """The finished episodes of each member, with copy indices as in its lone run."""
    out: list[list[dict]] = [[] for _ in range(population)]
    for episode in episodes:
        env_id = int(episode["env_id"])
        record = dict(episode)
        record["env_id"] = env_id % copies
        out[env_id // copies].append(record)
    return out
