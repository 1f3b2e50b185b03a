"""Counter-based random numbers, one independent stream per environment copy.

Every copy ``i`` of a batched task owns a 64-bit key (derived from ``seed + i``, the
Gymnasium vector-env convention) and a counter. Draw ``k`` of copy ``i`` is the
SplitMix64 finaliser of ``key_i + k * GAMMA``. A copy's random stream therefore does
not depend on how many other copies step beside it: copy ``i`` of a batched task seeded
with ``s`` is the same environment as a single copy seeded with ``s + i``.

Integer arithmetic only (int64 tensors, wrapping multiplication), so it runs unchanged
on any torch device and spawn decisions are exact integer comparisons.
"""

from __future__ import annotations

import numpy as np
import torch

_MASK64 = (1 << 64) - 1


def _signed(value: int) -> int:
    """Return the int64 two's-complement reading of an unsigned 64-bit value."""
    value &= _MASK64
    return value - (1 << 64) if value >= 1 << 63 else value


GAMMA = _signed(0x9E3779B97F4A7C15)
_C1 = _signed(0xBF58476D1CE4E5B9)
_C2 = _signed(0x94D049BB133111EB)
MASK32 = (1 << 32) - 1


def _srl(z: torch.Tensor, shift: int) -> torch.Tensor:
    """Logical right shift of int64 values (torch's ``>>`` is arithmetic)."""
    return (z >> shift) & ((1 << (64 - shift)) - 1)


def mix64(z: torch.Tensor) -> torch.Tensor:
    """SplitMix64 finaliser on int64 tensors (bijective, wrapping arithmetic)."""
    z = (z ^ _srl(z, 30)) * _C1
    z = (z ^ _srl(z, 27)) * _C2
    return z ^ _srl(z, 31)


def copy_keys(seed: int, num_envs: int, device: torch.device) -> torch.Tensor:
    """Return the stream keys of copies ``0..num_envs-1`` for a base ``seed``.

    Args:
        seed: Non-negative base seed; copy ``i`` gets the stream of seed ``seed + i``.
        num_envs: Number of copies.
        device: Torch device of the returned tensor.

    Returns:
        int64 tensor ``[num_envs]``.

    """
    base = torch.tensor(_signed(seed), dtype=torch.int64, device=device)
    seeds = base + torch.arange(num_envs, dtype=torch.int64, device=device)
    return mix64(mix64(seeds * GAMMA + GAMMA))


def entropy_seed() -> int:
    """Return a fresh seed from the operating system (used when no seed is given)."""
    return int(np.random.SeedSequence().entropy) & ((1 << 63) - 1)


def draw(keys: torch.Tensor, counters: torch.Tensor, offset: int = 0) -> torch.Tensor:
    """Return the 64-bit draw number ``counters + offset`` of each stream (int64)."""
    return mix64(keys + (counters + offset) * GAMMA)


def threshold32(probability: float) -> int:
    """Return ``T`` such that ``u32 < T`` has probability ``probability`` (to 2**-32)."""
    return round(probability * (1 << 32))
