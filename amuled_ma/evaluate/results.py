"""The evaluation's results as typed data: ``results.json`` and ``results.csv``.

Keys left unset are left out of ``results.json``.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from amuled_ma.files.safe import (
    atomic_writer,
    check_write_targets,
    checked_read_path,
    write_text_atomic,
)

#: The action selection modes a variant is evaluated in.
MODES = ("greedy", "sampled")
#: Largest ``results.json`` read [bytes]: 140 an episode plus 30 KB a trajectory per variant
#: and mode (the demo's: 0.6 MB).
MAX_RESULTS_BYTES = 256 * 2**20


class Stat(BaseModel):
    """Mean with a confidence interval (`mean_ci`)."""

    model_config = ConfigDict(extra="forbid")

    mean: float | None = None
    std: float | None = None
    n: int | None = None
    ci_low: float | None = None
    ci_high: float | None = None
    half_width: float | None = None


class Trajectory(BaseModel):
    """The first evaluation episode of copy 0: observations, actions, the task's events."""

    model_config = ConfigDict(extra="allow")

    obs: list[list[float]] = []
    actions: list[int] = []
    events: dict[str, list[float]] = {}
    layout: dict[str, Any] | None = None


class ModeResult(BaseModel):
    """A variant's evaluation in one mode (greedy or sampled)."""

    model_config = ConfigDict(extra="forbid")

    metrics: dict[str, Stat] = {}
    ci_over: str = "episodes"
    n_seeds: int = 1
    trajectory: Trajectory | None = None
    episodes: list[dict[str, float]] | None = None
    replicas: dict[str, dict[str, Stat]] | None = None


class FeedbackSummary(BaseModel):
    """A fine-tune's fused-belief diagnostics (its ``feedback.json``, merged over seeds)."""

    model_config = ConfigDict(extra="allow")

    feedback: str | None = None
    replicas: int | None = None
    steps: int | None = None
    unique_states: int | float | None = None
    mean_weight: dict[str, float] = {}
    mean_entropy_share: dict[str, float] = {}
    mean_conflict: float | None = None
    statuses: dict[str, int] = {}
    miss_rate: float = 0.0
    failure_rate: float = 0.0
    agents: dict[str, dict[str, int | float]] = {}
    agents_per_state: dict[str, dict[str, int | float]] = {}
    distill: dict[str, Any] | None = None
    llm_servers: dict[str, dict[str, Any]] | None = None


class PanelEntry(BaseModel):
    """What a fine-tune was trained on, as ``results.json`` keeps it (``"panel"``)."""

    model_config = ConfigDict(extra="forbid")

    feedback: str | None = None
    recipe: str | None = None
    lambda_kl: float | None = None
    iterations: int | None = None
    seed: int | None = None
    agents: list[str] | None = None
    source: str | None = None
    model: str | None = None
    recording: str | None = None
    fusion: str | None = None
    agent_sources: dict[str, dict[str, Any]] | None = None
    clusters_dirs: list[str] | None = None
    distill: dict[str, Any] | None = None
    inputs: dict[str, Any] | None = None
    base_checkpoint: str | None = None


class VariantResult(BaseModel):
    """One variant: its modes, and for a fine-tune its diagnostics and feedback."""

    model_config = ConfigDict(extra="forbid")

    greedy: ModeResult | None = None
    sampled: ModeResult | None = None
    feedback: FeedbackSummary | None = None
    panel: PanelEntry | None = None

    def modes(self) -> dict[str, ModeResult]:
        """``{mode: result}`` of the modes it was evaluated in."""
        return {m: r for m in MODES if (r := getattr(self, m)) is not None}

    def mode(self, mode: str) -> ModeResult | None:
        """Its result in ``mode`` (None if not evaluated in it)."""
        return getattr(self, mode) if mode in MODES else None


class Results(BaseModel):
    """A run's evaluation: every variant in every mode."""

    model_config = ConfigDict(extra="forbid")

    scenario: str | None = None
    task: str = ""
    episodes: int | None = None
    confidence: float = 0.95
    seed: int | None = None
    variants: dict[str, VariantResult] = {}

    def in_mode(self, mode: str) -> dict[str, ModeResult]:
        """``{variant: result}`` of the variants evaluated in ``mode``."""
        return {n: r for n, v in self.variants.items() if (r := v.mode(mode)) is not None}

    def to_data(self) -> dict[str, Any]:
        """Plain JSON data as ``results.json`` holds it (non-finite numbers as null)."""
        return _clean(self.model_dump(exclude_unset=True))


def _clean(value: object) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


#: The files `write_results` writes into a run folder.
RESULTS_FILES = ("results.json", "results.csv")


def write_results(run_dir: Path, results: Results) -> tuple[Path, Path]:
    """Write ``results.json`` and ``results.csv`` (a row per variant, mode, metric) atomically.

    UnsafePathError: either is a link or not a regular file (neither written); FileWriteError.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    json_path, csv_path = (run_dir / name for name in RESULTS_FILES)
    check_write_targets((json_path, csv_path))
    write_text_atomic(json_path, json.dumps(results.to_data(), indent=1))
    with atomic_writer(csv_path, text=True, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(
            ["variant", "mode", "metric", "mean", "ci_low", "ci_high", "std", "n", "ci_over"]
        )
        for variant, entry in results.variants.items():
            for mode, data in entry.modes().items():
                for metric, s in data.metrics.items():
                    writer.writerow(
                        [variant, mode, metric, _cell(s.mean), _cell(s.ci_low),
                         _cell(s.ci_high), _cell(s.std), s.n, data.ci_over]
                    )  # fmt: skip
    return json_path, csv_path


def _cell(value: float | None) -> float:
    return math.nan if value is None else value


def read_results(run_dir: Path) -> Results:
    """Read a run's ``results.json``; AmuledError: missing, unsafe, too large or not `Results`."""
    from pydantic import ValidationError

    from amuled_ma.errors import AmuledError
    from amuled_ma.files.limits import read_bounded_bytes

    path = checked_read_path(run_dir, "results.json")
    try:
        raw = read_bounded_bytes(
            path,
            MAX_RESULTS_BYTES,
            "results file",
            note="about 140 bytes an episode of each variant and mode",
            fix=f"is it the right folder? Evaluate the run again with 'amuled evaluate {run_dir}'",
        )
        return Results.model_validate_json(raw)
    except (OSError, ValidationError) as err:
        first = str(err).splitlines()[0]
        raise AmuledError(
            f"{path}: not readable results ({first}); evaluate the run again with "
            f"'amuled evaluate {run_dir}'"
        ) from None
