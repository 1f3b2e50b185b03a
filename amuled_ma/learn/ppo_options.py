"""Two CleanRL habits of the PPO update (``finetune_moral.py``) as options of ``AnchoredPPO``."""

from __future__ import annotations

from collections.abc import Generator
from typing import TYPE_CHECKING, Any

import torch
from rsl_rl.storage import RolloutStorage

if TYPE_CHECKING:
    from torch.utils.hooks import RemovableHandle


class EpochShuffledStorage(RolloutStorage):
    """rsl-rl's rollout storage whose mini-batches are re-partitioned in every epoch."""

    @classmethod
    def like(cls, storage: RolloutStorage) -> EpochShuffledStorage:
        """An empty storage of the same kind and shape as ``storage`` (the one rsl-rl built)."""
        return cls(
            storage.training_type,
            storage.num_envs,
            storage.num_transitions_per_env,
            storage.observations[0],  # one step of every observation group: [num_envs, ...]
            storage.actions_shape,
            storage.device,
        )

    def mini_batch_generator(
        self, num_mini_batches: int, num_epochs: int = 8
    ) -> Generator[RolloutStorage.Batch, None, None]:
        """Yield ``num_epochs`` epochs of mini-batches, each epoch a new partition."""
        for _ in range(num_epochs):
            yield from super().mini_batch_generator(num_mini_batches, 1)


def clip_jointly(optimizer: torch.optim.Optimizer, max_norm: float) -> RemovableHandle:
    """Clip all of ``optimizer``'s gradients as one vector before each step; the hook's handle.

    Raises ValueError: ``max_norm`` is not a positive finite number.
    """
    max_norm = float(max_norm)
    if not 0 < max_norm < float("inf"):
        raise ValueError(f"max_norm: expected a positive finite number, got {max_norm!r}")

    def hook(opt: torch.optim.Optimizer, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        params = [p for g in opt.param_groups for p in g["params"] if p.grad is not None]
        if params:
            torch.nn.utils.clip_grad_norm_(params, max_norm)

    return optimizer.register_step_pre_hook(hook)
