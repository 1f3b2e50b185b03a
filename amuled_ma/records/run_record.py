"""`RunRecord`: a run folder's ``config.json`` as typed data (its file: `run_folder`)."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, field_serializer, field_validator, model_validator

from amuled_ma.records.variants import Variant

#: The state of a variant folder's training.
State = Literal["complete", "interrupted", "failed"]


class Provenance(BaseModel):
    """Where an imported policy came from: ``file`` in ``checkout``, ``checkpoint``, ``model``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    repository: str | None = None
    checkout: str | None = None
    file: str | None = None
    sha256: str | None = None
    checkpoint: int | None = None
    model: str | None = None


class PanelRecord(BaseModel):
    """Who gave a fine-tune its feedback (``amuled``, ``cluster:care``, ``human``, ...).

    ``source``: the members' default source, ``agent_sources`` the others'; ``fused_only``: the
    authors' fused beliefs replayed (``fusion`` None); ``weights``: the prior weights' file.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    feedback: str
    members: list[str] = []
    source: str | None = None
    model: str | None = None
    recording: str | None = None
    fused_only: bool = False
    fusion: str | None = None
    agent_sources: dict[str, dict[str, Any]] = {}
    distill: dict[str, Any] | None = None
    weights: str | None = None


class RunRecord(BaseModel):
    """One ``config.json``: a run's (``variants``, ``seeds``, ...) or a variant folder's.

    ``name``: the variant in the run's results (its first seed's folder); ``training``: the
    settings and inputs' hashes compared before a resume or a skip (`training_config`);
    ``authors``: where an imported policy came from; ``shared``: an ablation's run folders.
    """

    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True)

    scenario: dict[str, Any] | None = None
    command: list[str] | None = None
    time: str | None = None
    torch: str | None = None
    rsl_rl: str | None = None
    variant: Variant | None = None
    label: str | None = None
    name: str | None = None
    seed: int | None = None
    training: dict[str, Any] | None = None
    panel: PanelRecord | None = None
    recipe: Literal["equation", "authors"] | None = None
    lambda_kl: float | None = None
    base_checkpoint: str | None = None
    iterations_done: int | None = None
    iterations_planned: int | None = None
    state: State | None = None
    authors: Provenance | None = None
    variants: list[str] | None = None
    seeds: list[int] | None = None
    ablation: str | None = None
    shared: list[str] | None = None

    @field_validator("variant", mode="before")
    @classmethod
    def _parse_variant(cls, value: Variant | str | None) -> Variant | None:
        return None if value is None else Variant.parse(value)

    @model_validator(mode="after")
    def _labelled(self) -> RunRecord:
        if self.variant is not None and self.label and self.variant.label != self.label:
            labelled = dataclasses.replace(self.variant, label=self.label)
            object.__setattr__(self, "variant", labelled)
        return self

    @field_serializer("variant")
    def _variant_text(self, variant: Variant | None) -> str | None:
        return None if variant is None else str(variant)

    def to_json(self) -> str:
        """The record as ``config.json`` holds it (unset fields left out)."""
        return self.model_dump_json(indent=2, exclude_none=True)

    @property
    def finetuning(self) -> bool:
        """Whether the folder holds a fine-tune."""
        return self.variant is not None and self.variant.finetuning

    @property
    def imported(self) -> bool:
        """Whether the policy was imported (the authors' CleanRL policy), not trained here."""
        return self.authors is not None and self.authors.file is not None

    @property
    def unfinished(self) -> bool:
        """Whether its training stopped before the planned iterations (or failed)."""
        return self.state in ("interrupted", "failed")
