"""The study folder's format as typed data: ``study.json`` read and written here only.

A study folder (``amuled study build``) holds:

- ``study.json``: :class:`Study`, every item with its state, its two options and which
  variant each option is (the participant never sees that part, see :func:`public_item`);
- ``states/<item>.svg``: the state of each item drawn (:mod:`amuled_ma.study.drawing`);
- ``consent.html``: the instructions and consent page, from a template the researcher edits
  (a rebuild keeps an edited one);
- ``answers.sqlite``: the participants' answers, written by ``amuled study serve``
  (:mod:`amuled_ma.study.answers`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from amuled_ma.errors import AmuledError

#: The study file's name in a study folder.
STUDY_FILE = "study.json"
#: The consent and instructions page.
CONSENT_FILE = "consent.html"
#: The answer store.
ANSWERS_FILE = "answers.sqlite"
#: The version of the folder format.
FORMAT = 1
#: What a participant is asked about a pair.
QUESTION = "Which decision is the more morally acceptable one in this situation?"


class StudyError(AmuledError, ValueError):
    """A study folder, a study's argument or an answer that does not fit the study."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Option(_Model):
    """One shown decision of an item.

    Attributes:
        label: ``A`` or ``B`` (what the participant sees; the order is random).
        variant: The variant that took it (hidden from the participant); None for an
            attention check.
        action: The action index.
        action_name: The task's name of the action.

    """

    label: Literal["A", "B"]
    variant: str | None
    action: int = Field(ge=0)
    action_name: str


class PanelView(_Model):
    """What the run's panel said about an item's state (from its belief store).

    Attributes:
        feedback: The variant whose panel answered (``amuled``, ...).
        agents: The panel members, in fusion order.
        rule: The fusion rule.
        beliefs: ``[K][A]`` each member's belief over the actions.
        statuses: ``[K]`` ``ok`` or why a member did not answer.
        fused: ``[A]`` the fused belief.

    """

    feedback: str
    agents: list[str]
    rule: str
    beliefs: list[list[float]]
    statuses: list[str]
    fused: list[float]


class Item(_Model):
    """One question of the study.

    Attributes:
        id: ``q001``, ... (stable, in the study's order).
        kind: ``pair`` (two variants' decisions) or ``attention`` (an instructed answer).
        run: Index into :attr:`Study.runs`.
        task: The task's name.
        episode: The evaluation episode the state was met in.
        step: Its step in that episode.
        met_by: The variant whose episode met the state.
        obs: The observation.
        prompt: The state in words (the task's prompt), None when it cannot be rendered.
        picture: ``states/<id>.svg``.
        options: The two options, in the order shown.
        expected: The label an attentive participant picks (attention checks only).
        instruction: The attention check's instruction (shown instead of the question).
        policies: Every studied variant's action in this state (the policies' agreement
            with the participants is read from it).
        panel: The run's panel about the state (None: no panel variant or no store).

    """

    id: str
    kind: Literal["pair", "attention"]
    run: int = Field(ge=0)
    task: str
    episode: int = Field(ge=0)
    step: int = Field(ge=0)
    met_by: str
    obs: list[float]
    prompt: str | None
    picture: str
    options: tuple[Option, Option]
    expected: Literal["A", "B"] | None = None
    instruction: str | None = None
    policies: dict[str, int] = Field(default_factory=dict)
    panel: PanelView | None = None


class Study(_Model):
    """A built study: ``study.json``.

    Attributes:
        format: :data:`FORMAT`.
        seed: The seed it was built with (same runs, variants, items and seed: same bytes).
        runs: The run folders, as given.
        variants: The compared variants (the names asked for).
        folders: ``[run][variant]`` the variant folders they resolved to.
        action_names: ``{task: [names]}``.
        question: What a pair asks.
        items: The questions, pairs and attention checks, in the study's order.
        candidates: How many distinct (state, pair of variants that differ) were found.

    """

    format: int = FORMAT
    seed: int
    runs: list[str]
    variants: list[str]
    folders: list[dict[str, str]]
    action_names: dict[str, list[str]]
    question: str = QUESTION
    items: list[Item]
    candidates: int = Field(ge=0)

    def item(self, item_id: str) -> Item | None:
        """The item of that id, None when the study has none."""
        for item in self.items:
            if item.id == item_id:
                return item
        return None


def write_study(folder: Path, study: Study) -> Path:
    """Write ``study.json`` (sorted keys, two-space indent, a final newline: stable bytes)."""
    path = Path(folder) / STUDY_FILE
    text = json.dumps(study.model_dump(mode="json"), indent=2, sort_keys=True)
    path.write_text(text + "\n", encoding="utf-8")
    return path


def read_study(folder: Path) -> Study:
    """Read a study folder's ``study.json``.

    Raises:
        StudyError: No such file, or it does not fit the format (the message names the key).

    """
    path = Path(folder) / STUDY_FILE
    if not path.is_file():
        raise StudyError(
            f"{folder}: no {STUDY_FILE}; build a study with 'amuled study build RUN... "
            f"--out {folder}'"
        )
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return Study.model_validate(data)
    except json.JSONDecodeError as exc:
        raise StudyError(f"{path}: not JSON ({exc}); rebuild the study") from exc
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise StudyError(
            f"{path}: key {where}: {first['msg']}; rebuild it with 'amuled study build'"
        ) from exc


#: What the picture shows, per task (under the picture).
LEGENDS = {
    "findmilk": "Black square: the robot. Gold star: the milk. Red discs: crying babies. "
    "Blue squares: sleeping babies. Up is up on the picture.",
    "driving": "Red: your car (bottom row). Grey: other cars. Green discs: grandmas to rescue. "
    "Everything ahead comes closer at each step.",
}


def public_item(item: Item, svg: str) -> dict[str, Any]:
    """What the participant's page gets of an item: no variant, no expected answer."""
    return {
        "id": item.id,
        "legend": LEGENDS.get(item.task, ""),
        "prompt": item.prompt,
        "svg": svg,
        "instruction": item.instruction,
        "options": [{"label": o.label, "action": o.action_name} for o in item.options],
    }
