"""`Variant`: what a training job trains, parsed once from its text (``finetune:cluster:care``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from amuled_ma.errors import ScenarioError

#: The aggregation baselines of ``agg:<rule>``: the simple rules, then the moral-uncertainty
#: rules (:mod:`amuled_ma.fusion.moral_uncertainty`).
AGGREGATIONS = ("mean", "max", "vote", "mec", "nash-vote", "variance-vote", "borda")

#: What a job trains.
Kind = Literal["base", "shaped", "finetune"]


def parse_feedback(feedback: str) -> tuple[str, str | None]:
    """``(kind, argument)`` of a feedback variant name; ScenarioError for an unknown one."""
    kind, _, arg = feedback.partition(":")
    if kind in ("amuled", "human", "moral") and not arg:
        return kind, None
    if kind == "human" and arg == "rules":
        return kind, arg
    if kind == "cluster" and arg:
        return kind, arg
    if kind == "agg" and arg in AGGREGATIONS:
        return kind, arg
    raise ScenarioError(
        f"unknown feedback variant {feedback!r}; expected amuled, human, human:rules, moral, "
        f"cluster:<name> or agg:{'|'.join(AGGREGATIONS)}"
    )


@dataclass(frozen=True)
class Variant:
    """One thing to train: ``base``, ``shaped`` or ``finetune`` (on ``feedback``, any name).

    ``label`` names the fine-tune's folder ``finetune-<label>`` instead of the feedback.
    """

    kind: Kind
    feedback: str | None = None
    label: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("base", "shaped", "finetune"):
            raise ScenarioError(
                f"unknown variant kind {self.kind!r}; expected base, shaped or finetune"
            )
        if self.kind == "finetune":
            if not self.feedback:
                raise ScenarioError("a fine-tune variant needs its feedback, e.g. finetune:amuled")
        elif self.feedback is not None:
            raise ScenarioError(f"variant {self.kind!r} takes no feedback ({self.feedback!r})")

    @classmethod
    def parse(cls, text: str | Variant, label: str | None = None) -> Variant:
        """Read ``base``, ``shaped`` or ``finetune:<feedback>`` (or a Variant); ScenarioError."""
        if isinstance(text, Variant):
            return text if label is None else cls(text.kind, text.feedback, label)
        if text == "base":
            return cls("base")
        if text == "shaped":
            return cls("shaped")
        kind, _, feedback = str(text).partition(":")
        if kind != "finetune":
            raise ScenarioError(
                f"unknown variant {text!r}; expected base, shaped or finetune:<feedback>"
            )
        return cls("finetune", feedback, label)

    @classmethod
    def finetune(cls, feedback: str, label: str | None = None) -> Variant:
        """The fine-tune on ``feedback`` (``amuled``, ``cluster:care``, ...)."""
        return cls("finetune", feedback, label)

    def __str__(self) -> str:
        return f"finetune:{self.feedback}" if self.kind == "finetune" else self.kind

    @property
    def finetuning(self) -> bool:
        """Whether this is a fine-tune (it needs a base policy and feedback)."""
        return self.kind == "finetune"

    @property
    def feedback_kind(self) -> tuple[str | None, str | None]:
        """``(kind, argument)`` of the feedback (:func:`parse_feedback`); ``(None, None)``."""
        return parse_feedback(self.feedback) if self.feedback else (None, None)

    @property
    def asks_panel(self) -> bool:
        """Whether the feedback comes from moral-cluster agents (not a demonstrator)."""
        return self.finetuning and self.feedback_kind[0] != "human"

    @property
    def folder(self) -> str:
        """The variant's folder in a run directory (``finetune-cluster-care``, ``base``)."""
        text = f"finetune-{self.label}" if self.label else str(self)
        return text.replace(":", "-").replace(" ", "_").replace("/", "_")
