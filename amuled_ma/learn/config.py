"""Build rsl-rl's training configuration (its 5.x dict schema) from a scenario.

rsl-rl's ``OnPolicyRunner`` mutates the dict it is given, so pass it a deep copy.
"""

from __future__ import annotations

from typing import Any

from amuled_ma.scenario import BaseConfig, FinetuneConfig, PPOConfig

#: Name of the single observation group handed to rsl-rl.
OBS_GROUP = "policy"

#: ``module:Class`` name of our PPO (rsl-rl's, anchored), resolved by rsl-rl.
ANCHORED_PPO = "amuled_ma.learn.anchored_ppo:AnchoredPPO"

#: ``module:Class`` name of our categorical distribution, resolved by rsl-rl.
CATEGORICAL = "amuled_ma.learn.distribution:CategoricalDistribution"

#: ``AnchoredPPO``'s CleanRL options and their defaults (rsl-rl's behaviour).
PPO_OPTION_DEFAULTS: dict[str, Any] = {
    "grad_clip": "per_network",
    "reshuffle_each_epoch": False,
    "bootstrap_time_outs": True,
}


def rsl_rl_config(
    ppo: PPOConfig,
    *,
    num_steps_per_env: int,
    learning_rate: float | None = None,
    num_learning_epochs: int | None = None,
    save_interval: int = 100,
    lambda_kl: float = 0.0,
    anchor: str = "per_sample",
    **ppo_options: Any,
) -> dict[str, Any]:
    """Return an rsl-rl 5.x ``train_cfg`` dict for a 2-layer categorical actor-critic.

    ``ppo_options`` are keys of `PPO_OPTION_DEFAULTS` (left out when equal to the default).
    Raises TypeError: an unknown key in ``ppo_options``.
    """
    unknown = sorted(set(ppo_options) - set(PPO_OPTION_DEFAULTS))
    if unknown:
        raise TypeError(f"rsl_rl_config: unknown PPO option(s) {', '.join(unknown)}")
    options = {k: v for k, v in ppo_options.items() if v != PPO_OPTION_DEFAULTS[k]}
    model = {
        "class_name": "rsl_rl.models:MLPModel",
        "hidden_dims": list(ppo.hidden_dims),
        "activation": ppo.activation,
        "obs_normalization": False,
    }
    return {
        "num_steps_per_env": int(num_steps_per_env),
        "save_interval": int(save_interval),
        "obs_groups": {"actor": [OBS_GROUP], "critic": [OBS_GROUP]},
        "check_for_nan": True,
        "logger": "tensorboard",
        "actor": {**model, "distribution_cfg": {"class_name": CATEGORICAL}},
        "critic": dict(model),
        "algorithm": {
            "class_name": ANCHORED_PPO,
            "lambda_kl": float(lambda_kl),
            "anchor": anchor,
            "adam_eps": 1e-5,
            "num_learning_epochs": int(num_learning_epochs or ppo.num_learning_epochs),
            "num_mini_batches": int(ppo.num_mini_batches),
            "clip_param": ppo.clip_param,
            "gamma": ppo.gamma,
            "lam": ppo.lam,
            # rsl-rl's value loss is coef * MSE; CleanRL's is vf_coef * 0.5 * MSE.
            "value_loss_coef": ppo.value_loss_coef * 0.5,
            "entropy_coef": ppo.entropy_coef,
            "learning_rate": float(
                learning_rate if learning_rate is not None else ppo.learning_rate
            ),
            "max_grad_norm": ppo.max_grad_norm,
            "optimizer": "adam",
            "use_clipped_value_loss": True,
            # We set the learning rate ourselves (CleanRL's linear annealing or constant).
            "schedule": "fixed",
            "desired_kl": None,
            "normalize_advantage_per_mini_batch": ppo.normalize_advantage_per_mini_batch,
            **options,
        },
    }


def planned_iterations(run: BaseConfig | FinetuneConfig) -> int:
    """PPO iterations of a fine-tune, or of a base run's ``total_steps`` (whole, at least one)."""
    if isinstance(run, FinetuneConfig):
        return int(run.iterations)
    return max(1, run.total_steps // (run.num_envs * run.num_steps_per_env))
