"""Two CleanRL habits of the PPO update, as options of our PPO (``AnchoredPPO``).

The AMULED authors fine-tuned with CleanRL's ``ppo.py`` loop (``finetune_moral.py``), whose
update differs from rsl-rl's in two places that this module reproduces through public
extension points only (rsl-rl's update loop is not copied):

- **Gradient clipping over actor and critic together.** CleanRL clips one norm over all
  the agent's parameters (``nn.utils.clip_grad_norm_(agent.parameters(), 0.5)``,
  ``finetune_moral.py:321``); rsl-rl clips the actor and the critic apart, each to
  ``max_grad_norm``. :func:`clip_jointly` registers a step pre-hook
  (:meth:`torch.optim.Optimizer.register_step_pre_hook`) that clips every parameter of
  the optimiser as one vector just before Adam's step; :class:`AnchoredPPO` then hands
  rsl-rl ``max_grad_norm = inf``, which makes its two clips multiply by exactly 1.
- **A new mini-batch partition in every epoch.** CleanRL shuffles the batch's indices
  at the start of every epoch (``np.random.shuffle(b_inds)``, ``finetune_moral.py:277``);
  rsl-rl's :meth:`~rsl_rl.storage.RolloutStorage.mini_batch_generator` draws one
  permutation per update and walks it ``num_epochs`` times. :class:`EpochShuffledStorage`
  calls rsl-rl's own generator once per epoch, for one epoch, so each epoch draws its
  own permutation.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import TYPE_CHECKING, Any

import torch
from rsl_rl.storage import RolloutStorage

if TYPE_CHECKING:
    from torch.utils.hooks import RemovableHandle


class EpochShuffledStorage(RolloutStorage):
    """rsl-rl's rollout storage whose mini-batches are re-partitioned in every epoch.

    Each epoch is one call of rsl-rl's :meth:`RolloutStorage.mini_batch_generator` with
    ``num_epochs = 1``: a fresh ``torch.randperm`` of the batch, cut into
    ``num_mini_batches`` mini-batches that cover every transition once.
    """

    @classmethod
    def like(cls, storage: RolloutStorage) -> EpochShuffledStorage:
        """An empty storage of the same kind and shape as ``storage`` (rsl-rl's, unused yet).

        Args:
            storage: The storage rsl-rl's ``construct_algorithm`` built.

        Returns:
            A new storage with the same training type, copies, rollout length,
            observation groups (shapes and dtypes), action shape and device.

        """
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
        """Yield ``num_epochs`` epochs of mini-batches, each epoch with a new partition.

        Args:
            num_mini_batches: Mini-batches per epoch.
            num_epochs: Epochs.

        Yields:
            rsl-rl's mini-batches, ``num_mini_batches`` per epoch.

        """
        for _ in range(num_epochs):
            yield from super().mini_batch_generator(num_mini_batches, 1)


def all_parameters(optimizer: torch.optim.Optimizer) -> list[torch.Tensor]:
    """Every parameter the optimiser updates, in its groups' order."""
    return [p for group in optimizer.param_groups for p in group["params"]]


def clip_jointly(optimizer: torch.optim.Optimizer, max_norm: float) -> RemovableHandle:
    """Clip the gradient of all of ``optimizer``'s parameters as one vector before each step.

    The norm is the 2-norm over every parameter's gradient together (actor and critic for
    :class:`~amuled_ma.learn.anchored_ppo.AnchoredPPO`), as CleanRL's
    ``clip_grad_norm_(agent.parameters(), max_norm)``.

    Args:
        optimizer: The optimiser whose steps are clipped.
        max_norm: Largest joint gradient norm (> 0).

    Returns:
        The hook's handle (``handle.remove()`` undoes it).

    Raises:
        ValueError: ``max_norm`` is not a positive finite number.

    """
    max_norm = float(max_norm)
    if not 0 < max_norm < float("inf"):
        raise ValueError(f"max_norm: expected a positive finite number, got {max_norm!r}")

    def hook(opt: torch.optim.Optimizer, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        params = [p for p in all_parameters(opt) if p.grad is not None]
        if params:
            torch.nn.utils.clip_grad_norm_(params, max_norm)

    return optimizer.register_step_pre_hook(hook)
