"""A panel weights file: one prior weight ``rho`` per panel member, named by ``[feedback].weights``.

``bjs-dst`` multiplies each member's credibility by it (``w_i ∝ rho_i · Crd_i · IV_i``), so
scale does not matter. ``amuled study fit-weights`` writes it; this module reads and checks it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Final, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from amuled_ma.errors import ScenarioError
from amuled_ma.files.limits import read_bounded_bytes

#: The version of the file's format.
WEIGHTS_FORMAT: Final = 1
#: Largest weights file read (a fitted one holds about 2,000 characters).
MAX_WEIGHTS_BYTES = 1_000_000
#: What the weights are, written into every fitted file.
MEANING = (
    "a prior on the panel members: bjs-dst multiplies each member's credibility by its weight "
    "(w_i proportional to rho_i * Crd_i * IV_i); fitted so that the fused belief best predicts "
    "these participants' choices in these states (docs/study.md)"
)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class HeldOut(_Model):
    """Held-out log-likelihood of the participants' choices, K folds over participants.

    ``fixed`` uses the uniform prior, ``learned`` the weights fitted on the other folds;
    ``difference_low``/``high`` are the 2.5/97.5% percentiles of ``learned - fixed`` over
    resampled participants.
    """

    folds: int = Field(ge=2)
    answers: int = Field(ge=0)
    fixed: float
    learned: float
    fixed_per_answer: float
    learned_per_answer: float
    difference_low: float
    difference_high: float


class WeightsProvenance(_Model):
    """Where fitted weights came from (``fixed_temperature`` None: the temperature was fitted)."""

    study: str
    study_sha256: str
    answers_sha256: str
    seed: int = Field(ge=0)
    bootstrap: int = Field(ge=0)
    keep_inattentive: bool = False
    fixed_temperature: float | None = Field(None, gt=0)
    command: str = "amuled study fit-weights"


class PanelWeights(_Model):
    """A panel weights file (JSON): one non-negative weight per member, not all zero, any scale.

    ``low``/``high`` are 2.5/97.5% bootstrap percentiles of fitted weights; ``rule`` is
    ``bjs-dst`` only.
    """

    format: Literal[1] = WEIGHTS_FORMAT
    rule: Literal["bjs-dst"] = "bjs-dst"
    meaning: str = MEANING
    members: list[str] = Field(min_length=1, max_length=1000)
    weights: list[float] = Field(min_length=1, max_length=1000)
    low: list[float] | None = None
    high: list[float] | None = None
    temperature: float | None = Field(None, gt=0)
    temperature_interval: tuple[float, float] | None = None
    participants: int | None = Field(None, ge=0)
    answers: int | None = Field(None, ge=0)
    items: int | None = Field(None, ge=0)
    held_out: HeldOut | None = None
    provenance: WeightsProvenance | None = None

    @field_validator("members")
    @classmethod
    def _members_are_distinct(cls, value: list[str]) -> list[str]:
        seen = set()
        for name in value:
            if not name or name in seen:
                raise ValueError(f"member {name!r} is empty or listed twice")
            seen.add(name)
        return value

    @field_validator("weights")
    @classmethod
    def _weights_are_a_prior(cls, value: list[float]) -> list[float]:
        if any(not (w >= 0 and math.isfinite(w)) for w in value):
            raise ValueError(f"every weight must be a finite number >= 0, found {value}")
        if not sum(value) > 0:
            raise ValueError("the weights are all zero: at least one member needs weight")
        return value

    @model_validator(mode="after")
    def _one_weight_per_member(self) -> PanelWeights:
        for key in ("weights", "low", "high"):
            values = getattr(self, key)
            if values is not None and len(values) != len(self.members):
                raise ValueError(f"{key} has {len(values)} values for {len(self.members)} members")
        return self


def weights_prior(
    weights: str, members: Sequence[str], resolve: Callable[[str], Path], where: str
) -> tuple[float, ...]:
    """The prior of a ``[feedback].weights`` file in ``members``' order, scaled to sum 1.

    Raises:
        ScenarioError: The file is missing, not JSON or malformed; a panel member without a
            weight, a weight for a non-member, or no weight above 0 among the members.
    """
    where = f"{where}: key [feedback].weights"
    path = resolve(weights)
    fix = "write it with 'amuled study fit-weights STUDY' (docs/study.md)"
    try:
        raw = read_bounded_bytes(
            path,
            MAX_WEIGHTS_BYTES,
            "weights file",
            error=ScenarioError,
            head=f"{where}: weights file {path}",
        )
    except OSError:
        raise ScenarioError(f"{where}: weights file {path} not found; {fix}") from None
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        why = "nested deeper than Python can read" if isinstance(error, RecursionError) else error
        raise ScenarioError(f"{where}: weights file {path} is not JSON ({why}); {fix}") from None
    try:
        panel = PanelWeights.model_validate(data)
    except ValidationError as error:
        first = error.errors()[0]
        key = ".".join(str(p) for p in first["loc"]) or "(the whole file)"
        message = str(first["msg"]).removeprefix("Value error, ")
        raise ScenarioError(f"{where}: weights file {path}: key {key}: {message}; {fix}") from None
    total = math.fsum(panel.weights)
    known = {m: w / total for m, w in zip(panel.members, panel.weights, strict=True)}
    missing = [m for m in members if m not in known]
    extra = [m for m in known if m not in members]
    fix = (
        "fit weights for this panel ('amuled study fit-weights STUDY' on a study of a run "
        "with these members) or drop [feedback].weights"
    )
    if missing:
        raise ScenarioError(
            f"{where}: weights file {path} has no weight for the panel member "
            f"{missing[0]!r} (it names {', '.join(known)}); {fix}"
        )
    if extra:
        raise ScenarioError(
            f"{where}: weights file {path} weighs {extra[0]!r}, which is not a member of the "
            f"panel ([feedback].clusters: {', '.join(members)}); {fix}"
        )
    return tuple(known[m] for m in members)
