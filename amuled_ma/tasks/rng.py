"""Counter-based random numbers (SplitMix64), one independent stream per environment copy.

Draw ``k`` of copy ``i`` is the SplitMix64 finaliser of ``key_i + k * GAMMA`` (key from
``seed + i``); int64 wrapping arithmetic only, so it runs unchanged on any torch device.
"""

from __future__ import annotations

import secrets

import torch

__all__ = [
    "GAMMA",
    "MASK32",
    "copy_keys",
    "draw",
    "draws",
    "entropy_seed",
    "mix64",
    "shift_right",
    "splitmix64",
    "threshold32",
    "uniform53",
]

_MASK64 = (1 << 64) - 1


def _signed(value: int) -> int:
    """Return the int64 two's-complement reading of an unsigned 64-bit value."""
    value &= _MASK64
    return value - (1 << 64) if value >= 1 << 63 else value


GAMMA = _signed(0x9E3779B97F4A7C15)
"""The SplitMix64 increment (golden ratio), as an int64."""
_C1 = _signed(0xBF58476D1CE4E5B9)
_C2 = _signed(0x94D049BB133111EB)
MASK32 = (1 << 32) - 1
"""The low 32 bits of a draw."""


def shift_right(z: torch.Tensor, shift: int) -> torch.Tensor:
    """Return the logical right shift (1..63 bits) of int64 values (``>>`` is arithmetic)."""
    return (z >> shift) & ((1 << (64 - shift)) - 1)


def mix64(z: torch.Tensor) -> torch.Tensor:
    """SplitMix64 finaliser on int64 tensors (bijective, wrapping arithmetic)."""
    z = (z ^ shift_right(z, 30)) * _C1
    z = (z ^ shift_right(z, 27)) * _C2
    return z ^ shift_right(z, 31)


def splitmix64(value: int) -> int:
    """Return the SplitMix64 output of the state ``value`` mod 2**64 (the scalar `mix64`)."""
    state = torch.tensor(_signed(value + GAMMA), dtype=torch.int64)
    return int(mix64(state)) & _MASK64


def copy_keys(seed: int, num_envs: int, device: torch.device) -> torch.Tensor:
    """Return the stream keys int64 ``[num_envs]`` of copies ``i`` (seed ``seed + i``)."""
    base = torch.tensor(_signed(seed), dtype=torch.int64, device=device)
    seeds = base + torch.arange(num_envs, dtype=torch.int64, device=device)
    return mix64(mix64(seeds * GAMMA + GAMMA))


def entropy_seed() -> int:
    """Return a fresh seed from the operating system (used when no seed is given)."""
    return secrets.randbits(63)


def draw(keys: torch.Tensor, counters: torch.Tensor, offset: int = 0) -> torch.Tensor:
    """Return the 64-bit draw number ``counters + offset`` of each stream (int64)."""
    return mix64(keys + (counters + offset) * GAMMA)


def draws(keys: torch.Tensor, counters: torch.Tensor | int, count: int) -> torch.Tensor:
    """Return draws ``counters .. counters + count - 1`` of each stream, int64 ``[N, count]``."""
    first = torch.as_tensor(counters, dtype=torch.int64, device=keys.device)[..., None]
    offsets = first + torch.arange(count, dtype=torch.int64, device=keys.device)
    return mix64(keys[:, None] + offsets * GAMMA)


def uniform53(z: torch.Tensor) -> torch.Tensor:
    """Return draws as float64 uniforms in ``[0, 1)`` (their top 53 bits)."""
    return shift_right(z, 11).to(torch.float64) * 2.0**-53


def threshold32(probability: float) -> int:
    """Return ``T`` such that ``u32 < T`` has probability ``probability`` (to 2**-32)."""
    return round(probability * (1 << 32))
