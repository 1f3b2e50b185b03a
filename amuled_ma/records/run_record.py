"""`RunRecord`: a run folder's ``config.json`` as typed data (its file: `run_folder`)."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, field_serializer, field_validator, model_validator

from amuled_ma.records.variants import Variant

#: The state of a variant folder's training.
State = Literal["complete", "interrupted", "failed"]


class Provenance(BaseModel):
    """Where an imported policy (or an imported run) came from.

    ``checkout`` is the checkout it was imported from, ``file`` the policy file relative to it;
    ``checkpoint`` the authors' PPO iteration of a fine-tune (``N`` of ``ppo_<N>``), ``model``
    the LLM of its feedback.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    repository: str | None = None
    checkout: str | None = None
    file: str | None = None
    sha256: str | None = None
    checkpoint: int | None = None
    model: str | None = None


class PanelRecord(BaseModel):
    """Who gave a fine-tune its feedback (``amuled``, ``cluster:care``, ``human``, ...).

    ``members`` is empty for a demonstrator or a fused-only recording; ``source`` is where the
    members' beliefs come from by default (``replay``, ``ollama``, ``rules``, ...), and
    ``agent_sources`` the members with a source of their own. ``fused_only``: the recording keeps
    only the authors' fused belief per state, replayed as it is (no panel asked, no fusion of
    ours; ``fusion`` None). ``distill``: the ``[feedback.distill]`` settings of a panel asked on a
    budget. ``weights``: the file of the members' prior weights ``bjs-dst`` used (None: the
    paper's fixed weights).
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

    ``variant`` is what the folder trains, ``label`` its fine-tune label (`Variant.label`);
    ``name`` is the variant's name in the run's results, its first seed's folder
    (``finetune-amuled`` also for ``finetune-amuled.seed2``). ``training`` holds the settings that
    decide what it learns and the inputs' hashes, compared before a resume or a skip
    (`training_config`). ``recipe`` and ``lambda_kl`` are a fine-tune's KL anchor and
    coefficient, ``base_checkpoint`` the checkpoint it started from; ``state`` is ``interrupted``
    when stopped or still to resume. ``authors``: where an imported policy or run came from;
    ``ablation`` and ``shared``: an ablation folder's ablation and the run's folders it is
    evaluated with.
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
