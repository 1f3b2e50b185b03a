r"""The study server's request bodies as strict pydantic models: every field bounded at the edge.

An answer is read in two steps: the `AnswerEnvelope` first, then the item's `answer_models`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
    create_model,
)

#: The longest participant id, item id, token or source accepted [characters].
MAX_TEXT = 200
#: The longest time an answer may report [ms]: 24 h.
MAX_MS = 86_400_000
#: The most judgements an expert answer may hold (one per action; the tasks have 4 or 3).
MAX_ACTIONS = 64

#: A short non-empty string (pydantic's parser has already refused what is not UTF-8).
Text = Annotated[str, StringConstraints(min_length=1, max_length=MAX_TEXT)]
#: A time taken [ms]: a finite number in ``[0, MAX_MS)``.
Time = Annotated[float, Field(ge=0, lt=MAX_MS, allow_inf_nan=False)]


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class SessionRequest(_Request):
    """``POST /api/session``: all optional (no id: the server assigns one)."""

    participant: Text | None = None
    token: Text | None = None
    source: Text | None = None


class AnswerEnvelope(BaseModel):
    """``POST /api/answer``, first step: who answers which item (the rest read later)."""

    model_config = ConfigDict(extra="allow", frozen=True, strict=True)

    participant: Text
    token: Text
    item: Text
    choice: Text | None = None


class Ratings(_Request):
    """A pair's two ratings; `answer_models` bounds them to the study's scale (strict integers)."""

    A: int
    B: int


class PairAnswer(_Request):
    """``POST /api/answer`` for a pair; `answer_models` bounds it to the study's scales."""

    participant: Text
    token: Text
    item: Text
    choice: Literal["A", "B"]
    ms: Time
    ratings: Ratings


class Judged(_Request):
    """An expert's judgement of one action; `answer_models` bounds the framework."""

    acceptable: bool
    framework: str


class ExpertAnswerRequest(_Request):
    """``POST /api/answer`` for an expert; `answer_models` bounds it to the study's scales."""

    participant: Text
    token: Text
    item: Text
    ms: Time
    actions: list[Judged] = Field(max_length=MAX_ACTIONS)
    clarity: int | None = None


def answer_models(
    rating_points: int, clarity_points: int, frameworks: list[str]
) -> tuple[type[PairAnswer], Callable[[int, bool], type[ExpertAnswerRequest]]]:
    """The model of a pair's answer, and of an expert's by ``(actions, reason)``, on the scales.

    An expert's holds one judgement per action citing one of ``frameworks``, and a clarity
    exactly when the panel stated a ``reason``.
    """
    rating = (int, Field(strict=True, ge=1, le=rating_points))
    ratings = create_model("ScaledRatings", __base__=Ratings, A=rating, B=rating)
    pair_model = create_model("ScaledPairAnswer", __base__=PairAnswer, ratings=(ratings, ...))
    cited = Literal[tuple(frameworks)]  # type: ignore[valid-type]

    class CitedJudged(Judged):
        framework: cited  # type: ignore[valid-type]

    @functools.cache
    def expert_model(actions: int, reason: bool) -> type[ExpertAnswerRequest]:
        return create_model(
            "ScaledExpertAnswer",
            __base__=ExpertAnswerRequest,
            actions=(list[CitedJudged], Field(min_length=actions, max_length=actions)),
            clarity=(int, Field(strict=True, ge=1, le=clarity_points)) if reason else (None, None),
        )

    return pair_model, expert_model


def first_error(error: ValidationError) -> tuple[tuple[str | int, ...], str, str]:
    """The first error's ``(location, type, message)``, for the refusal and its reply."""
    first = error.errors(include_url=False, include_input=False)[0]
    return tuple(first["loc"]), str(first["type"]), str(first["msg"])


def where(loc: tuple[str | int, ...]) -> str:
    """``ratings.A``, ``actions.2.framework``: a location as the reply names it."""
    return ".".join(str(part) for part in loc) or "body"


#: The refusal's reason kept for an answer whose first error is in this field (an expert's
#: judgement: ``actions.N.<field>``).
REASONS = {
    "choice": "unknown choice",
    "ms": "bad time",
    "acceptable": "expert: acceptable not yes or no",
    "framework": "expert: unknown framework",
}


def refusal_reason(loc: tuple[str | int, ...], kind: str) -> str:
    """The refusal's reason kept for an answer that does not fit its item's model."""
    head = str(loc[0]) if loc else ""
    if head not in ("ratings", "clarity", "actions", "choice", "ms") or (
        len(loc) == 1 and kind == "extra_forbidden"  # a field of the other kind of item
    ):
        return f"answer: unexpected or malformed field {where(loc)}"
    if head == "ratings":
        if len(loc) == 1 or kind == "missing":
            return "ratings missing"
        if kind == "extra_forbidden":
            return "rating for an option not shown"
        return "rating outside the scale"
    if head == "clarity":
        if kind == "none_required":
            return "clarity without a stated reason"
        return "clarity outside the scale"
    if head == "actions":
        if len(loc) == 1:
            return "expert: not one judgement per action"
        field = str(loc[2]) if len(loc) > 2 and kind != "extra_forbidden" else ""
        return REASONS.get(field, "expert: judgement malformed")
    return REASONS[head]
