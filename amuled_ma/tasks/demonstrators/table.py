"""A demonstrator's counts as a belief table: observation keys, the 0.6 / 0.4 rule, the file.

Keys, the rule, unseen observations and the ``.npz`` file (no pickle): docs/tasks.md.
"""

from __future__ import annotations

import functools
import json
import math
import os
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from amuled_ma.errors import AmuledError
from amuled_ma.files.limits import check_size
from amuled_ma.files.safe import atomic_writer, checked_read_path
from amuled_ma.tasks import canonical_name, get_task
from amuled_ma.tasks.base import check_int

FORMAT_VERSION = 1
DEFAULT_EPISODES: Mapping[str, int] = {"findmilk": 1000, "driving": 10_000}
"""Episodes the authors played per task."""
DRIVING_COUNT_FROM = 601
"""First counted Driving episode (the authors' ``if cnt > 600``)."""
AUTHORS_STATE_COUNTS: Mapping[str, int] = {"findmilk": 1120, "driving": 12_270}
"""Distinct observations of the authors' demonstrator pickles (their notebook's figures)."""
MAX_STEPS = 300
"""Time limit of an episode (both tasks, the authors' 300 steps)."""

MAX_TABLE_BYTES = 2**30
"""Most bytes a demonstrator file, and its arrays once loaded, may take (1 GiB): 10,000 Driving
episodes of 300 steps meet at most 3,000,000 states (about 150 MB)."""

# counts -> belief (finetune_moral_human.py)
COUNT_CAP = 20.0
P_AGREE = 0.6


class DemonstratorCacheError(AmuledError, ValueError):
    """A demonstrator cache file is unreadable, malformed or made with other settings."""


def check_table_memory(path: Path, fix: str) -> None:
    """Refuse a demonstrator ``.npz`` whose arrays would take more than `MAX_TABLE_BYTES`.

    Reads only the zip directory and the ``.npy`` headers: ``np.load`` allocates what a header
    claims before it reads, so a small file could claim terabytes. ``fix`` is said last.

    Raises:
        DemonstratorCacheError: The file is too large, not a zip of ``.npy`` arrays, holds
            Python objects, or claims more bytes than it holds or than `MAX_TABLE_BYTES`.
    """
    total = 0
    try:
        check_size(
            path,
            MAX_TABLE_BYTES,
            "demonstrator table",
            error=DemonstratorCacheError,
            note="the authors' Driving table is under 1 MB",
            fix=fix,
        )
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
                    else:
                        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
                if dtype.hasobject:
                    raise ValueError(f"array {info.filename} holds Python objects")
                nbytes = math.prod(int(n) for n in shape) * dtype.itemsize  # exact, no overflow
                name = f"{info.filename} (shape {tuple(shape)} of {dtype})"
                if nbytes > info.file_size:
                    raise ValueError(
                        f"{name} claims {nbytes:,} bytes but its member holds {info.file_size:,}"
                    )
                total += nbytes
                if total > MAX_TABLE_BYTES:
                    raise DemonstratorCacheError(
                        f"{path}: its arrays would take {total:,} bytes of memory or more "
                        f"({name} alone {nbytes:,}), more than the {MAX_TABLE_BYTES:,} a "
                        "demonstrator table may take (the authors' Driving table takes "
                        f"under 1 MB); it is not loaded; {fix}"
                    )
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        if isinstance(err, DemonstratorCacheError):
            raise
        reason = " ".join(str(err).split())[:200]
        raise DemonstratorCacheError(
            f"{path}: not a readable demonstrator cache ({reason}); {fix}"
        ) from err


def observation_bounds(task_name: str) -> list[list[int]]:
    """Return the integer ``[low, high]`` of each observation entry (the keys' radixes)."""
    cls = get_task(task_name)
    return [
        [math.floor(lo), math.ceil(hi)] for lo, hi in zip(cls.obs_low, cls.obs_high, strict=True)
    ]


@functools.cache
def _encoder(task_name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """CPU tensors ``low``, ``high`` (float64) and the int64 place value of each entry."""
    bounds = observation_bounds(task_name)
    weight, place = [], 1
    for lo, hi in reversed(bounds):
        weight.append(place)
        place *= hi - lo + 1
    if place >= 1 << 62:
        raise ValueError(f"{task_name}: observation bounds too wide for int64 keys")
    return (
        torch.tensor([b[0] for b in bounds], dtype=torch.float64),
        torch.tensor([b[1] for b in bounds], dtype=torch.float64),
        torch.tensor(weight[::-1], dtype=torch.int64),
    )


def encode_observations(task_name: str, obs: object) -> tuple[torch.Tensor, torch.Tensor]:
    """Return each observation's exact key (``-1``: none) and whether it has one, ``[N]``.

    A row has a key when integer-valued within the bounds; on ``obs``'s device (CPU: not a tensor).

    Raises:
        ValueError: ``obs`` is not ``[N, obs_dim]``.
    """
    name = canonical_name(task_name)
    low, high, weight = _encoder(name)
    values = obs if isinstance(obs, torch.Tensor) else torch.as_tensor(np.asarray(obs))
    if values.ndim != 2 or values.shape[1] != low.numel():
        raise ValueError(
            f"obs: expected shape [N, {low.numel()}] for task {name!r}, got {tuple(values.shape)}"
        )
    if values.device != low.device:
        low, high, weight = low.to(values.device), high.to(values.device), weight.to(values.device)
    values = values.to(torch.float64)
    valid = ((values == values.round()) & (values >= low) & (values <= high)).all(1)
    digits = torch.where(valid[:, None], values - low, 0.0).to(torch.int64)
    keys = (digits * weight).sum(1)
    return torch.where(valid, keys, -1), valid


def counts_to_belief(counts: object) -> torch.Tensor:
    """Turn action counts ``[..., A]`` into float64 beliefs (``finetune_moral_human.py``)."""
    c = torch.as_tensor(counts).to(torch.float64)
    n = c.sum(-1, keepdim=True)
    c = torch.where(n > COUNT_CAP, c * COUNT_CAP / n, c)
    n = c.sum(-1, keepdim=True)
    log_p = c * math.log(P_AGREE) + (n - c) * math.log(1.0 - P_AGREE)  # 0.6**c_a 0.4**(n-c_a)
    return torch.softmax(log_p, -1)


def demonstrator_settings(task_name: str, *, seed: int, episodes: int | None = None) -> dict:
    """Return the JSON-ready settings a demonstrator belief of the authors' recipe is built with."""
    name = canonical_name(task_name)
    seed = check_int(seed, "seed")
    episodes = check_int(DEFAULT_EPISODES[name] if episodes is None else episodes, "episodes", 1)
    return {
        "format": FORMAT_VERSION,
        "task": name,
        "demonstrator": "rules" if name == "findmilk" else "sarsa",
        "seed": seed,
        "episodes": episodes,
        "count_from": 0 if name == "findmilk" else DRIVING_COUNT_FROM,
        "max_steps": MAX_STEPS,
        "encoding": observation_bounds(name),
    }


def settings_differences(found: Mapping[str, Any], expect: Mapping[str, Any]) -> str:
    """Describe the keys of ``expect`` whose value in ``found`` differs (``""``: none)."""
    return ", ".join(
        f"{k}: file {found.get(k)!r}, wanted {v!r}" for k, v in expect.items() if found.get(k) != v
    )


class DemonstratorBelief:
    """Counts of a played demonstrator and the beliefs they give, keyed by observation.

    ``states`` are strictly increasing keys int64 ``[S]``; ``counts`` int64 ``[S, A]``, every
    row summing to at least 1.

    Raises:
        ValueError: The arrays are malformed; the message says which.
    """

    def __init__(
        self,
        task_name: str,
        states: torch.Tensor,
        counts: torch.Tensor,
        settings: Mapping[str, Any],
    ) -> None:
        self.task_name = canonical_name(task_name)
        num_actions = len(get_task(self.task_name).action_names)
        states = torch.as_tensor(states).to(device="cpu", dtype=torch.int64).reshape(-1)
        counts = torch.as_tensor(counts).to(device="cpu", dtype=torch.int64)
        if counts.shape != (states.numel(), num_actions):
            raise ValueError(
                f"counts: expected shape ({states.numel()}, {num_actions}) for "
                f"{states.numel()} states of {self.task_name!r}, got {tuple(counts.shape)}"
            )
        if states.numel() > 1 and not bool((states[1:] > states[:-1]).all()):
            raise ValueError("states: expected strictly increasing observation keys")
        if bool((states < 0).any()) or bool((counts < 0).any()):
            raise ValueError("states/counts: expected non-negative values")
        if bool((counts.sum(1) < 1).any()):
            raise ValueError("counts: every state needs at least one counted action")
        self.states = states
        self.counts = counts
        self.beliefs = counts_to_belief(counts)
        self.settings = dict(settings)

    @property
    def num_states(self) -> int:
        """Number of distinct observations the demonstrator met."""
        return int(self.states.numel())

    @property
    def num_actions(self) -> int:
        """Number of actions of the task."""
        return int(self.counts.shape[1])

    def lookup(self, obs: object) -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``(beliefs, seen)``, exact matches: float32 ``[N, A]`` (0: unseen), bool ``[N]``.

        On ``obs``'s device.

        Raises:
            ValueError: ``obs`` is not ``[N, obs_dim]``.
        """
        device = obs.device if isinstance(obs, torch.Tensor) else torch.device("cpu")
        keys, valid = encode_observations(self.task_name, obs)
        keys = keys.cpu()
        where = torch.searchsorted(self.states, keys).clamp_(max=max(self.num_states - 1, 0))
        if self.num_states:
            seen = valid.cpu() & (self.states[where] == keys)
            beliefs = torch.where(seen[:, None], self.beliefs[where], 0.0)
        else:
            seen = torch.zeros(keys.numel(), dtype=torch.bool)
            beliefs = torch.zeros(keys.numel(), self.num_actions, dtype=torch.float64)
        return beliefs.to(device=device, dtype=torch.float32), seen.to(device)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the counts and settings to ``path`` (``.npz``, no pickle) atomically; return it.

        Raises:
            UnsafePathError: ``path`` is a link or not a regular file.
            FileWriteError: It could not be written (a full disk); the old file is kept.
        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_writer(path) as f:
            np.savez_compressed(
                f,
                states=self.states.numpy(),
                counts=self.counts.numpy(),
                task=np.array(self.task_name),
                settings=np.array(json.dumps(self.settings, sort_keys=True)),
            )
        return path

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, expect: Mapping[str, Any] | None = None
    ) -> DemonstratorBelief:
        """Read a file written by `save`, made with ``expect``'s settings (None: any).

        Raises:
            DemonstratorCacheError: The file cannot be read, is malformed, its arrays would
                take more than `MAX_TABLE_BYTES`, or it was made with other settings.
        """
        path = checked_read_path(Path(path).parent, Path(path).name)
        fix = "delete it to rebuild the demonstrator"
        check_table_memory(path, fix)
        try:
            with np.load(path, allow_pickle=False) as data:
                states = data["states"]
                counts = data["counts"]
                task = str(data["task"])
                settings = json.loads(str(data["settings"]))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as err:
            # a damaged member: a bad CRC (BadZipFile), a broken deflate stream (zlib.error)
            raise DemonstratorCacheError(
                f"{path}: not a readable demonstrator cache ({err}); {fix}"
            ) from err
        if not isinstance(settings, dict):
            raise DemonstratorCacheError(f"{path}: settings are not a JSON object; {fix}")
        if expect is not None:
            differ = settings_differences(settings, expect)
            if differ:
                raise DemonstratorCacheError(
                    f"{path}: made with other settings ({differ}); {fix}, or ask for those"
                )
        try:
            return cls(task, torch.from_numpy(states), torch.from_numpy(counts), settings)
        except (ValueError, TypeError) as err:
            raise DemonstratorCacheError(
                f"{path}: malformed demonstrator cache ({err}); {fix}"
            ) from err
