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

    Attributes:
        repository: The authors' repository.
        checkout: The checkout it was imported from (the run's record).
        file: The policy file, relative to the checkout.
        sha256: The SHA-256 of that file.
        checkpoint: The authors' PPO iteration of a fine-tune (``N`` of ``ppo_<N>``).
        model: The LLM of the fine-tune's feedback.

    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    repository: str | None = None
    checkout: str | None = None
    file: str | None = None
    sha256: str | None = None
    checkpoint: int | None = None
    model: str | None = None


class PanelRecord(BaseModel):
    """Who gave a fine-tune its feedback, in plain terms.

    Attributes:
        feedback: The feedback variant (``amuled``, ``cluster:care``, ``human``, ...).
        members: The panel's agents (empty for a demonstrator or a fused-only recording).
        source: Where the members' beliefs come from by default (``replay``, ``ollama``,
            ``rules``, ...).
        model: The LLM of the beliefs (an Ollama model, or the recording's).
        recording: The replayed recording's file name.
        fused_only: The recording keeps only the authors' fused belief per state: it was
            replayed as it is, no panel was asked and no fusion of ours ran.
        fusion: The fusion rule (None where nothing is fused).
        agent_sources: Members with a source of their own (``[feedback.agents]``).
        distill: The ``[feedback.distill]`` settings, when the panel was asked on a budget.
        weights: The file name of the members' prior weights (``[feedback].weights``) the
            ``bjs-dst`` fusion used; None: the paper's fixed weights.

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

    Attributes:
        scenario: The fully resolved scenario, as plain data.
        command: The command line that wrote it.
        time: When it was written.
        torch: torch's version.
        rsl_rl: rsl-rl-lib's version.
        variant: What the folder trains (a run made by ``amuled train``: what it trained).
        label: The fine-tune's folder label (:attr:`Variant.label`).
        name: The variant's name in the run's results: its first seed's folder
            (``finetune-amuled`` also for ``finetune-amuled.seed2``).
        seed: The training seed.
        training: The settings that decide what it learns and the inputs' hashes, compared
            before a resume or a skip (:func:`~amuled_ma.experiments.run_folder.
            training_config`).
        panel: Who gave a fine-tune its feedback.
        recipe: The fine-tune's KL anchor (``equation`` or ``authors``).
        lambda_kl: The fine-tune's KL coefficient.
        base_checkpoint: The checkpoint a fine-tune started from and is anchored to.
        iterations_done: PPO iterations in its checkpoint.
        iterations_planned: PPO iterations it was asked to train.
        state: ``complete``, ``interrupted`` (stopped, or still to resume) or ``failed``.
        authors: Where an imported policy or run came from.
        variants: A run's variants.
        seeds: A run's training seeds.
        ablation: An ablation folder's ablation.
        shared: The run's folders an ablation is evaluated with.

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
