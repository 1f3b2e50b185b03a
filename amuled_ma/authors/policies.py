"""Convert the authors' CleanRL policies into our run folders (docs/authors.md).

Their ``{actor,critic}.{0,2,4}`` become rsl-rl's ``mlp.{0,2,4}``; both actors must give the same
logits. Files are read with ``weights_only=True``: tensors only, no code.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from amuled_ma.errors import CheckpointError
from amuled_ma.files.safe import atomic_writer, write_text_atomic
from amuled_ma.files.torch_load import load_weights_only
from amuled_ma.records.variants import Variant

if TYPE_CHECKING:
    from rsl_rl.models import MLPModel

    from amuled_ma.scenario import Changes, FinetuneConfig, PPOConfig

#: Layer indices of CleanRL's ``nn.Sequential`` (Linear, Tanh, Linear, Tanh, Linear).
CLEANRL_LINEARS = (0, 2, 4)
#: The activation between the authors' layers.
CLEANRL_ACTIVATION = "tanh"
#: PPO iterations of the authors' base runs: their ``ppo.py`` with 500,000 steps and 8
#: copies x 128 steps per iteration (``--num-envs 8``, their README and Driving's logged
#: ``num_iterations``).
AUTHORS_BASE_ITERATIONS = 488
#: Seed of every published run (the ``_42`` of ``models/<Env>_42``).
AUTHORS_SEED = 42
#: Steps per copy and copies of one fine-tuning iteration (128 transitions).
AUTHORS_FINETUNE_STEPS = 128
#: Largest absolute difference of logits accepted between the two networks.
LOGIT_TOLERANCE = 1e-5

_PPO_FILE = re.compile(r"^ppo_(\d+)\.cleanrl_model$")

#: The rsl-rl config an imported variant folder holds beside its checkpoint.
TRAIN_CFG = "train_cfg.json"


def last_checkpoint(folder: Path) -> tuple[Path, int] | None:
    """The ``ppo_<N>.cleanrl_model`` of a folder with the highest ``N`` (above 0), and ``N``."""
    found = [
        (int(m.group(1)), p)
        for p in Path(folder).glob("ppo_*.cleanrl_model")
        if (m := _PPO_FILE.match(p.name)) and int(m.group(1))
    ]
    if not found:
        return None
    n, path = max(found)
    return path, n


def read_cleanrl(path: str | Path) -> dict[str, torch.Tensor]:
    """Load a CleanRL ``Agent`` state dict (weights only, float32 on the CPU) and check its layout.

    Raises:
        CheckpointError: Missing, needs code to load (refused; nothing ran), or not the keys
            and shapes of the authors' ``Agent``.
    """
    path = Path(path)
    state = load_weights_only(path, "the CleanRL policy")
    expected = {f"{net}.{i}.{p}" for net in ("actor", "critic") for i in CLEANRL_LINEARS
                for p in ("weight", "bias")}  # fmt: skip
    if not isinstance(state, Mapping) or set(state) != expected:
        keys = sorted(map(str, state)) if isinstance(state, Mapping) else type(state).__name__
        raise CheckpointError(
            f"{path}: not the authors' CleanRL Agent (expected the keys "
            f"{{actor,critic}}.{{0,2,4}}.{{weight,bias}}, found {keys})"
        )
    state = dict(state)
    for key, tensor in state.items():
        if not (isinstance(tensor, torch.Tensor) and tensor.is_floating_point()):
            raise CheckpointError(f"{path}: {key} is not a float tensor")
        if not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{path}: {key} holds NaN or infinite weights")
    cleanrl_shape(state, path)
    return state


def cleanrl_shape(
    state: Mapping[str, torch.Tensor], where: object = "policy"
) -> tuple[int, list[int], int]:
    """``(obs_dim, hidden dims, num_actions)`` of a CleanRL state dict; checks every shape.

    Raises:
        CheckpointError: A shape does not chain (naming ``where``).
    """
    layers: dict[str, list[torch.Tensor]] = {}
    for net, out in (("actor", None), ("critic", 1)):
        weights = layers[net] = [state[f"{net}.{i}.weight"] for i in CLEANRL_LINEARS]
        biases = [state[f"{net}.{i}.bias"] for i in CLEANRL_LINEARS]
        ok = all(w.dim() == 2 for w in weights) and all(
            b.dim() == 1 and b.shape[0] == w.shape[0] for w, b in zip(weights, biases, strict=True)
        )
        ok = ok and all(nxt.shape[1] == w.shape[0] for w, nxt in pairwise(weights))
        if not ok or (out is not None and weights[-1].shape[0] != out):
            shapes = {
                f"{net}.{i}.weight": tuple(w.shape)
                for i, w in zip(CLEANRL_LINEARS, weights, strict=True)
            }
            raise CheckpointError(f"{where}: the {net}'s layer shapes do not chain: {shapes}")
    actor, critic = layers["actor"], layers["critic"]
    hidden = [int(w.shape[0]) for w in actor[:-1]]
    if [int(w.shape[0]) for w in critic[:-1]] != hidden or critic[0].shape[1] != actor[0].shape[1]:
        raise CheckpointError(f"{where}: actor and critic have different shapes")
    return int(actor[0].shape[1]), hidden, int(actor[-1].shape[0])


def build_networks(ppo: PPOConfig, obs_dim: int, num_actions: int) -> tuple[MLPModel, MLPModel]:
    """Our ``(actor, critic)`` (rsl-rl ``MLPModel``) of ``ppo``'s shape, as training builds them."""
    from amuled_ma.learn.policies import build_model

    return (
        build_model(ppo, "actor", obs_dim, num_actions),
        build_model(ppo, "critic", obs_dim, 1),
    )


def copy_weights(state: Mapping[str, torch.Tensor], net: str, model: torch.nn.Module) -> None:
    """Copy CleanRL's ``<net>.{0,2,4}`` into the Linear layers of ``model``, in order.

    Raises:
        CheckpointError: Our network has another number or shape of layers.
    """
    ours = [m for m in model.modules() if isinstance(m, torch.nn.Linear)]
    if len(ours) != len(CLEANRL_LINEARS):
        raise CheckpointError(
            f"our {net} has {len(ours)} Linear layers, the authors' {len(CLEANRL_LINEARS)}"
        )
    with torch.no_grad():
        for layer, i in zip(ours, CLEANRL_LINEARS, strict=True):
            weight, bias = state[f"{net}.{i}.weight"], state[f"{net}.{i}.bias"]
            if layer.weight.shape != weight.shape:
                raise CheckpointError(
                    f"{net}.{i}.weight is {tuple(weight.shape)}, our layer "
                    f"{tuple(layer.weight.shape)}"
                )
            layer.weight.copy_(weight)
            layer.bias.copy_(bias)


def authors_changes(hidden: list[int]) -> Changes:
    """The authors' network (``hidden`` units, tanh) and seed, as changes to a scenario.

    ``hidden`` from :func:`cleanrl_shape`; for :meth:`~amuled_ma.scenario.Scenario.changed`.
    """
    return (
        ("ppo", {"hidden_dims": list(hidden), "activation": CLEANRL_ACTIVATION}),
        ("task", {"seed": AUTHORS_SEED}),
    )


def build_checkpoint(
    state: Mapping[str, torch.Tensor],
    ppo: PPOConfig,
    finetune: FinetuneConfig,
    *,
    scenario_name: str,
    variant: Variant,
    iteration: int,
    base_checkpoint: Path | None = None,
    source: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Our checkpoint (a ``model_last.pt``'s dict) of a CleanRL policy; ``source``: its ``authors``.

    Raises:
        CheckpointError: The ``[ppo]`` networks do not fit the policy, or the converted
            actor's logits differ from the CleanRL actor's.
    """
    from amuled_ma.learn.anchored_ppo import adam
    from amuled_ma.learn.config import rsl_rl_config

    obs_dim, _hidden, num_actions = cleanrl_shape(state)
    actor, critic = build_networks(ppo, obs_dim, num_actions)
    copy_weights(state, "actor", actor)
    copy_weights(state, "critic", critic)
    check_equivalent(state, actor)
    lr = float(finetune.learning_rate if variant.finetuning else ppo.learning_rate)
    optimizer = adam([*actor.parameters(), *critic.parameters()], lr=lr, eps=1e-5)
    train_cfg = rsl_rl_config(
        ppo,
        num_steps_per_env=AUTHORS_FINETUNE_STEPS,
        learning_rate=lr,
        save_interval=5,
        num_learning_epochs=8 if variant.finetuning else None,
    )
    infos = {
        "variant": str(variant),
        "scenario": scenario_name,
        "iteration": iteration,
        "total_iterations": iteration,
        "completed": True,
        "curve": [],
        "wall_s": 0.0,
        "torch_rng": torch.Generator().manual_seed(AUTHORS_SEED).get_state(),
        "train_cfg": train_cfg,
        "base_checkpoint": str(base_checkpoint) if base_checkpoint else None,
        "num_actions": num_actions,
        "obs_dim": obs_dim,
        "authors": dict(source or {}),
    }
    return {
        "actor_state_dict": actor.state_dict(),
        "critic_state_dict": critic.state_dict(),
        "optimizer_state_dict": optimizer.state_dict(),
        "iter": iteration,
        "infos": infos,
    }


def check_equivalent(
    state: Mapping[str, torch.Tensor], actor: MLPModel, samples: int = 256
) -> None:
    """Check that our actor gives the CleanRL actor's logits on random observations.

    Raises:
        CheckpointError: The logits differ by more than `LOGIT_TOLERANCE`.
    """
    obs_dim = int(state["actor.0.weight"].shape[1])
    gen = torch.Generator().manual_seed(0)
    obs = torch.randint(-2, 9, (samples, obs_dim), generator=gen).float()
    with torch.no_grad():
        theirs = obs  # their ``Agent.actor``: Linear, tanh, Linear, tanh, Linear
        for k, i in enumerate(CLEANRL_LINEARS):
            weight, bias = state[f"actor.{i}.weight"], state[f"actor.{i}.bias"]
            theirs = torch.nn.functional.linear(theirs, weight, bias)
            if k < len(CLEANRL_LINEARS) - 1:
                theirs = torch.tanh(theirs)
        ours = actor.mlp(actor.obs_normalizer(obs))
    diff = float((theirs - ours).abs().max())
    if not diff <= LOGIT_TOLERANCE:
        raise CheckpointError(
            f"the converted actor's logits differ from the CleanRL actor's by {diff:.3g} "
            f"(tolerance {LOGIT_TOLERANCE:g}); the scenario's [ppo] network does not match"
        )


def write_variant(
    out_dir: Path,
    checkpoint: Mapping[str, Any],
    scenario: Mapping[str, Any],
    *,
    training: Mapping[str, Any],
) -> Path:
    """Write a completed variant folder: ``model_last.pt``, ``config.json``, ``train_cfg.json``.

    ``training`` (the authors' settings) makes a resume with others refused; returns the checkpoint.
    """
    import json

    from amuled_ma.experiments.run_folder import write_config
    from amuled_ma.learn.checkpoints import LAST
    from amuled_ma.records.run_record import RunRecord

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / LAST
    with atomic_writer(path) as handle:
        torch.save(dict(checkpoint), handle)
    infos = checkpoint["infos"]
    fields: dict[str, Any] = {
        "variant": infos["variant"],
        "name": out_dir.name,
        "seed": training.get("seed"),
        "training": dict(training),
        "iterations_planned": infos["total_iterations"],
        "iterations_done": infos["iteration"],
        "state": "complete" if infos["completed"] else "interrupted",
        "authors": dict(infos["authors"]),
    }
    variant = RunRecord.model_validate({"variant": infos["variant"]}).variant  # its one parser
    if variant is not None and variant.finetuning:  # the authors' panel's feedback, this LLM
        fields["panel"] = {"feedback": variant.feedback, "model": infos["authors"].get("model")}
    write_config(out_dir, scenario, fields)
    write_text_atomic(out_dir / TRAIN_CFG, json.dumps(infos["train_cfg"], indent=2))
    return path
