"""Trained policies outside training (rsl-rl's public API): load an actor, read its log-probs."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDict

from amuled_ma.errors import CheckpointError
from amuled_ma.learn.checkpoints import read_checkpoint
from amuled_ma.learn.config import OBS_GROUP, rsl_rl_config

if TYPE_CHECKING:
    from rsl_rl.models import MLPModel

    from amuled_ma.scenario import PPOConfig


def action_log_probs(actor: MLPModel, obs: torch.Tensor) -> torch.Tensor:
    """Return ``log pi(.|s)`` ``[N, A]`` of an rsl-rl actor with our categorical head."""
    actor(TensorDict({OBS_GROUP: obs}, batch_size=[obs.shape[0]], device=obs.device))
    (log_probs,) = actor.output_distribution_params
    return log_probs


def build_model(ppo: PPOConfig, role: str, obs_dim: int, outputs: int) -> MLPModel:
    """Build an untrained ``"actor"`` or ``"critic"`` ``MLPModel`` of the scenario's shape."""
    from rsl_rl.models import MLPModel

    cfg = dict(rsl_rl_config(ppo, num_steps_per_env=1)[role])
    cfg.pop("class_name")
    obs = TensorDict({OBS_GROUP: torch.zeros(1, obs_dim)}, batch_size=[1])
    return MLPModel(obs, {role: [OBS_GROUP]}, role, outputs, **cfg)


def load_policy(checkpoint: Path, ppo: PPOConfig) -> MLPModel:
    """The actor of a job's checkpoint in eval mode, shaped by the ``[ppo]`` it was trained with.

    Raises CheckpointError: the file is missing or unreadable, or its actor does not fit.
    """
    state = read_checkpoint(checkpoint)
    infos = state.get("infos") or {}
    weights = state["actor_state_dict"]
    try:
        obs_dim = (
            infos.get("obs_dim") or next(v for k, v in weights.items() if "weight" in k).shape[1]
        )
        num_actions = infos.get("num_actions") or list(weights.values())[-1].shape[0]
        actor = build_model(ppo, "actor", int(obs_dim), int(num_actions))
        actor.load_state_dict(weights)
    except (AttributeError, IndexError, RuntimeError, StopIteration, TypeError) as error:
        raise CheckpointError(
            f"checkpoint {checkpoint}: its actor does not fit the scenario's network ({error}); "
            "evaluate it with the scenario it was trained on, or retrain it with --force"
        ) from error
    actor.eval()
    return actor
