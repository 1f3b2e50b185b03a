"""The study folder's format as typed data: ``study.json`` is read and written here only.

A study folder holds ``study.json``, ``states/<item>.svg``, ``consent.html`` and ``answers.sqlite``.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from amuled_ma.errors import AmuledError
from amuled_ma.files.safe import file_kind, write_text_atomic

#: The study file's name in a study folder.
STUDY_FILE = "study.json"
#: The consent and instructions page.
CONSENT_FILE = "consent.html"
#: The answer store.
ANSWERS_FILE = "answers.sqlite"
#: Largest ``study.json`` read [bytes]: about 3 KB an item, so some 20,000 items.
MAX_STUDY_BYTES = 64 * 2**20
#: The folder format (a format 1 study reads as pairs with the default rating scale).
FORMAT = 2
#: What a participant is asked about a pair.
QUESTION = "Which decision is the more morally acceptable one in this situation?"
#: What a participant is asked about each decision of a pair, on the rating scale.
RATING_QUESTION = "How morally acceptable is each decision?"
#: Points of the acceptability scale (1 = completely unacceptable ... 7 = completely acceptable).
RATING_POINTS = 7
#: Points of the expert's clarity scale (1 = not clear at all ... 5 = very clear).
CLARITY_POINTS = 5
#: The expert's framework answer when none of the panel's clusters justifies an action.
NO_FRAMEWORK = "none"
#: What the page shows of a member whose reply kept no reason.
NO_REASON = "no stated reason recorded"


class StudyError(AmuledError, ValueError):
    """A study folder, a study's argument or an answer that does not fit the study."""


class NotInFolder(StudyError):
    """A study folder's file that is a symbolic link, not a regular file, or outside it."""


def read_folder_file(
    folder: Path,
    relative: str,
    limit: int,
    noun: str,
    *,
    note: str,
    fix: str,
) -> str:
    """A regular UTF-8 file inside a study folder (no link), of at most ``limit`` bytes.

    NotInFolder: a link, not a regular file, or outside; StudyError: too large, unreadable or
    not UTF-8.
    """
    from amuled_ma.files.limits import decode_text, too_large

    path = Path(folder) / relative
    refuse = f"{path}: the {noun} must be a regular file inside the study folder, "
    redo = "; replace it by the file itself (rebuild the study with 'amuled study build')"
    try:
        inside = path.resolve().is_relative_to(Path(folder).resolve())
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | getattr(os, "O_NONBLOCK", 0))
    except OSError as failure:
        if os.path.islink(path):
            link = f"found a symbolic link to {os.readlink(path)}"
            raise NotInFolder(refuse + link + redo) from None
        raise StudyError(
            f"{path}: cannot read the {noun}: {failure.strerror or failure}; check the path"
        ) from failure
    with os.fdopen(fd, "rb") as handle:
        info = os.fstat(handle.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise NotInFolder(refuse + f"found {file_kind(path, info.st_mode)}{redo}")
        if not inside:
            raise NotInFolder(refuse + f"it resolves to {path.resolve()}{redo}")
        if info.st_size > limit:
            raise StudyError(too_large(f"{path}: the {noun}", info.st_size, limit, noun,
                                       note=note, fix=fix))  # fmt: skip
        data = handle.read(limit + 1)
    if len(data) > limit:
        raise StudyError(f"{path}: the {noun} holds more than the {limit:,} bytes it may; {fix}")
    return decode_text(path, data, noun, error=StudyError)


def check_run_folders(runs: list[Path]) -> None:
    """Refuse a run folder that does not exist (StudyError), before anything is read."""
    for run in runs:
        if not Path(run).is_dir():
            what = "is not a folder" if Path(run).exists() else "does not exist"
            raise StudyError(
                f"{run}: the run folder {what}; give a run folder of 'amuled run' or "
                "'amuled train' (is the path right?)"
            )


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Option(_Model):
    """One shown decision of an item; ``variant`` is hidden, None for an attention check."""

    label: Literal["A", "B"]
    variant: str | None
    action: int = Field(ge=0)
    action_name: str


class PanelView(_Model):
    """What the run's panel said about a state: ``beliefs`` ``[K][A]``, ``reasons`` ``[K]``."""

    feedback: str
    agents: list[str]
    rule: str
    beliefs: list[list[float]]
    statuses: list[str]
    fused: list[float]
    reasons: list[str | None] = Field(default_factory=list)

    def has_reasons(self) -> bool:
        """Whether any member's reply kept a stated reason."""
        return any(self.reasons)


#: An item's ``picture``: an SVG directly in ``states/``, so a foreign study.json cannot make
#: ``study serve`` send other files of the machine.
PICTURE_PATTERN = r"^states/[A-Za-z0-9_-]+\.svg$"


class Item(_Model):
    """One question: a ``pair``, an ``attention`` check (``expected``) or an ``expert`` state.

    ``policies``: each studied variant's action; ``panel`` None without a panel variant or store.
    """

    id: str
    kind: Literal["pair", "attention", "expert"]
    run: int = Field(ge=0)
    task: str
    episode: int = Field(ge=0)
    step: int = Field(ge=0)
    met_by: str
    obs: list[float]
    prompt: str | None
    picture: str = Field(pattern=PICTURE_PATTERN)
    options: tuple[Option, Option] | tuple[()] = ()
    expected: Literal["A", "B"] | None = None
    instruction: str | None = None
    policies: dict[str, int] = Field(default_factory=dict)
    panel: PanelView | None = None

    @model_validator(mode="after")
    def _options_fit_the_kind(self) -> Item:
        want = 0 if self.kind == "expert" else 2
        if len(self.options) != want:
            raise ValueError(f"a {self.kind} item has {want} options, found {len(self.options)}")
        if want and [o.label for o in self.options] != ["A", "B"]:
            raise ValueError("options: expected the labels A then B")
        return self


class Study(_Model):
    """A built study: ``study.json``; ``folders`` ``[run][variant]``."""

    format: int = FORMAT
    mode: Literal["pairs", "expert"] = "pairs"
    seed: int
    runs: list[str]
    variants: list[str]
    folders: list[dict[str, str]]
    action_names: dict[str, list[str]]
    question: str = QUESTION
    rating_question: str = RATING_QUESTION
    rating_points: int = Field(RATING_POINTS, ge=2, le=11)
    clarity_points: int = Field(CLARITY_POINTS, ge=2, le=11)
    frameworks: list[tuple[str, str]] = Field(default_factory=list)
    items: list[Item]
    candidates: int = Field(ge=0)

    def framework_names(self) -> list[str]:
        """The frameworks an expert may cite, `NO_FRAMEWORK` last."""
        return [name for name, _ in self.frameworks] + [NO_FRAMEWORK]

    def item(self, item_id: str) -> Item | None:
        """The item of that id, None when the study has none."""
        return next((item for item in self.items if item.id == item_id), None)


def write_study(folder: Path, study: Study) -> Path:
    """Write ``study.json`` (sorted keys, indent 2: stable bytes) by ``write_text_atomic``."""
    path = Path(folder) / STUDY_FILE
    text = json.dumps(study.model_dump(mode="json"), indent=2, sort_keys=True)
    return write_text_atomic(path, text + "\n")


def read_study(folder: Path) -> Study:
    """Read a study folder's ``study.json``; StudyError naming the key where it does not fit."""
    path = Path(folder) / STUDY_FILE
    if not path.is_file() and not path.is_symlink():
        raise StudyError(
            f"{folder}: no {STUDY_FILE}; build a study with 'amuled study build RUN... "
            f"--out {folder}'"
        )
    text = read_folder_file(
        Path(folder),
        STUDY_FILE,
        MAX_STUDY_BYTES,
        "study file",
        note="about 3 KB an item",
        fix="is it the right folder? Rebuild the study with 'amuled study build'",
    )
    try:  # pydantic's parser: nesting deeper than it follows is a JSON error, not a crash
        return Study.model_validate_json(text)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        if first["type"] == "json_invalid":
            raise StudyError(f"{path}: not JSON ({first['msg']}); rebuild the study") from None
        where = ".".join(str(p) for p in first["loc"])
        raise StudyError(
            f"{path}: key {where}: {first['msg']}; rebuild it with 'amuled study build'"
        ) from None


#: What the picture shows, per task (under the picture).
LEGENDS = {
    "findmilk": "Dark square: the robot. Gold star: the milk. Orange discs (C): crying babies. "
    "Sky-blue squares (z): sleeping babies. Up is up on the picture.",
    "driving": "Dark: your car (bottom row). Orange-red: other cars. Green discs: grandmas to "
    "rescue. Everything ahead comes closer at each step.",
}


def public_item(item: Item, svg: str, action_names: list[str] | None = None) -> dict[str, Any]:
    """What the participant's page gets of an item (an expert: the panel), never the variant."""
    shown: dict[str, Any] = {
        "id": item.id,
        "kind": item.kind,
        "legend": LEGENDS.get(item.task, ""),
        "prompt": item.prompt,
        "svg": svg,
        "instruction": item.instruction,
        "options": [{"label": o.label, "action": o.action_name} for o in item.options],
    }
    if item.kind == "expert":
        shown["actions"] = list(action_names or [])
        panel = item.panel
        shown["panel"] = None
        if panel is not None:
            reasons = panel.reasons or [None] * len(panel.agents)
            shown["panel"] = {
                "members": [
                    {"name": name, "belief": belief, "status": status, "reason": reason}
                    for name, belief, status, reason in zip(
                        panel.agents, panel.beliefs, panel.statuses, reasons, strict=True
                    )
                ],
                "fused": panel.fused,
            }
        shown["has_reasons"] = panel is not None and panel.has_reasons()
    return shown
