"""``amuled study serve``: the study's participant page and its answer API (Starlette).

Routes (all served from this process; the page loads nothing from the network):

- ``GET /``: the participant page (jsPsych 7, shipped in ``amuled_ma/study/static``); a
  recruiting platform's id comes in the URL (``?PROLIFIC_PID=``, ``?workerId=``,
  ``?participant=``);
- ``GET /consent``: the study folder's ``consent.html`` (the researcher's text);
- ``POST /api/session``: ``{"participant", "token", "source"}`` (all optional) gives the
  participant's id and token and the items left, in the participant's own order (drawn
  from the study's seed and the id, so a reload shows the same order);
- ``POST /api/answer``: a pair's ``{"participant", "token", "item", "choice", "ms",
  "ratings": {"A": r, "B": r}}`` (``r`` an integer of the study's acceptability scale, one per
  shown option), or an expert state's ``{"participant", "token", "item", "ms", "actions":
  [{"acceptable": true, "framework": "care"}, ...] (one per action of the task), "clarity": c}``
  (``c`` on the clarity scale, ``null`` where the panel stated no reason); stored at once
  (200), or refused: a wrong token (403), an unknown item, choice, time, a rating outside
  the scale or for an option not shown, a judgement that does not fit (400), an item
  already answered by that participant (409), a body over :data:`MAX_BODY_BYTES` (413, on
  both POST routes, not read further). Every refusal is kept with its reason.
- ``GET /api/health``: ``{"ok": true, "items": n}``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from amuled_ma.study.answers import Answer, AnswerStore, ExpertAnswer, Judgement
from amuled_ma.study.model import (
    ANSWERS_FILE,
    CONSENT_FILE,
    NO_FRAMEWORK,
    NO_REASON,
    Item,
    Study,
    StudyError,
    public_item,
    read_study,
)

STATIC = Path(__file__).parent / "static"
#: URL parameters a recruiting platform puts the participant's id in.
ID_PARAMETERS = ("PROLIFIC_PID", "workerId", "participant")
#: The longest participant id, item id or token accepted.
MAX_TEXT = 200
#: Largest state picture read [bytes] (``states/<item>.svg``, each sent to every
#: participant): a drawn state is about 3 KB; 4 MiB is over 1,000 times that.
MAX_PICTURE_BYTES = 4 * 2**20
#: Largest consent page read [bytes] (``consent.html``, the researcher's text, read at
#: start and at each request so an edit shows at once): the shipped templates are about
#: 2 KB; 16 MiB leaves room for pictures inlined as ``data:`` URLs.
MAX_CONSENT_BYTES = 16 * 2**20
#: Largest request body read [bytes]: an answer is a few hundred bytes (an expert's, one
#: judgement per action, under 1 KB); a longer body is refused (413) unread.
MAX_BODY_BYTES = 64 * 2**10
#: What the page shows without a consent file.
NO_CONSENT = "<p>(no consent page)</p>"
#: What a participant is shown when the consent file is refused (the reason goes to the
#: server's stderr, not to the participant).
CONSENT_REFUSED = "<p>(the consent page cannot be shown; please tell the researcher)</p>"


def _is_time(ms: Any) -> bool:
    """A time taken in ms: a finite number in ``[0, 24 h)``."""
    return (
        not isinstance(ms, bool)
        and isinstance(ms, int | float)
        and math.isfinite(ms)
        and 0 <= ms < 86_400_000
    )


def _on_scale(value: Any, points: int) -> bool:
    """An integer (not a bool, not a float) from 1 to ``points``."""
    return isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= points


def rating_problem(ratings: Any, item: Item, points: int) -> str | None:
    """Why a pair's ratings are refused (the reason kept), None when they fit."""
    labels = [o.label for o in item.options]
    if not isinstance(ratings, dict):
        return "ratings missing"
    if any(label not in labels for label in ratings):
        return "rating for an option not shown"
    if any(label not in ratings for label in labels):
        return "ratings missing"
    if not all(_on_scale(ratings[label], points) for label in labels):
        return "rating outside the scale"
    return None


def expert_problem(body: dict[str, Any], item: Item, study: Study) -> str | None:
    """Why an expert's answer is refused (the reason kept), None when it fits."""
    actions = body.get("actions")
    n = len(study.action_names.get(item.task, []))
    if not isinstance(actions, list) or len(actions) != n:
        return "expert: not one judgement per action"
    frameworks = study.framework_names()
    for judged in actions:
        if not isinstance(judged, dict) or set(judged) != {"acceptable", "framework"}:
            return "expert: judgement malformed"
        if not isinstance(judged["acceptable"], bool):
            return "expert: acceptable not yes or no"
        if judged["framework"] not in frameworks:
            return "expert: unknown framework"
    clarity = body.get("clarity")
    if item.panel is not None and item.panel.has_reasons():
        if not _on_scale(clarity, study.clarity_points):
            return "clarity outside the scale"
    elif clarity is not None:
        return "clarity without a stated reason"
    return None


class _BodyTooLarge(Exception):
    """A request body over :data:`MAX_BODY_BYTES` (answered 413, not read further)."""


def _too_large() -> JSONResponse:
    return JSONResponse(
        {"error": f"the body is more than the {MAX_BODY_BYTES:,} bytes an answer may be"},
        status_code=413,
    )


def participant_order(study: Study, participant: str) -> list[str]:
    """The item ids in the order this participant sees them (seed and id decide it)."""
    digest = hashlib.sha256(f"{study.seed}:{participant}".encode()).digest()
    rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))
    ids = [item.id for item in study.items]
    return [ids[i] for i in rng.permutation(len(ids)).tolist()]


class StudyApp:
    """The server's state: the study, its pictures and its answer store.

    Args:
        folder: The study folder (``amuled study build``).

    Raises:
        StudyError: The folder holds no study, or its ``study.json``, a state picture or
            ``consent.html`` is over its cap (:data:`~amuled_ma.study.model.MAX_STUDY_BYTES`,
            :data:`MAX_PICTURE_BYTES`, :data:`MAX_CONSENT_BYTES`), unreadable or not UTF-8;
            one line naming the file, before anything is served.

    """

    def __init__(self, folder: Path) -> None:
        from amuled_ma.file_limits import read_bounded_text

        self.folder = Path(folder)
        self.study = read_study(self.folder)
        self.pictures = {
            item.id: read_bounded_text(
                self.folder / item.picture,
                MAX_PICTURE_BYTES,
                "state picture",
                error=StudyError,
                note="a drawn state is about 3 KB",
                fix="is it the right folder? Rebuild the study with 'amuled study build'",
            )
            for item in self.study.items
        }
        self.consent_text()  # an unreadable consent page stops the start, with one line
        self.items = {item.id: item for item in self.study.items}
        self.store = AnswerStore(self.folder / ANSWERS_FILE)
        self.app = Starlette(
            routes=[
                Route("/", self.page),
                Route("/consent", self.consent),
                Route("/api/session", self.session, methods=["POST"]),
                Route("/api/answer", self.answer, methods=["POST"]),
                Route("/api/health", self.health),
                Mount("/static", StaticFiles(directory=str(STATIC)), name="static"),
            ],
            lifespan=self._lifespan,
        )

    @contextlib.asynccontextmanager
    async def _lifespan(self, app: Starlette) -> AsyncIterator[None]:
        yield
        self.store.close()

    async def page(self, request: Request) -> Response:
        """The participant page."""
        return HTMLResponse((STATIC / "study.html").read_text(encoding="utf-8"))

    def consent_text(self) -> str:
        """The study folder's ``consent.html`` (:data:`NO_CONSENT` without one).

        Raises:
            StudyError: It is larger than :data:`MAX_CONSENT_BYTES` (refused from its size,
                before it is read), unreadable or not UTF-8; one line naming it.

        """
        from amuled_ma.file_limits import read_bounded_text

        path = self.folder / CONSENT_FILE
        if not path.is_file():
            return NO_CONSENT
        return read_bounded_text(
            path,
            MAX_CONSENT_BYTES,
            "consent page",
            error=StudyError,
            note="the shipped templates are about 2 KB",
            fix="is it the right file? Edit it down, or rebuild the study to get the template",
        )

    async def consent(self, request: Request) -> Response:
        """The researcher's consent and instructions fragment (500 when it is refused).

        A file refused (edited since the start) is said in one line on the server's stderr;
        the participant gets :data:`CONSENT_REFUSED`, without the folder's path.
        """
        try:
            return HTMLResponse(self.consent_text())
        except StudyError as refused:
            print(f"amuled study serve: {refused}", file=sys.stderr, flush=True)
            return HTMLResponse(CONSENT_REFUSED, status_code=500)

    async def health(self, request: Request) -> Response:
        """Whether the server is up, with its counts."""
        return JSONResponse({"ok": True, "items": len(self.items)})

    async def _json(self, request: Request) -> dict[str, Any] | None:
        """The request's JSON object, None when it is none.

        Raises:
            _BodyTooLarge: The body is over :data:`MAX_BODY_BYTES` (declared or sent); it
                is not read further.

        """
        declared = request.headers.get("content-length", "")
        if declared.isdigit() and int(declared) > MAX_BODY_BYTES:
            raise _BodyTooLarge
        chunks: list[bytes] = []
        size = 0
        async for chunk in request.stream():
            size += len(chunk)
            if size > MAX_BODY_BYTES:
                raise _BodyTooLarge
            chunks.append(chunk)
        try:
            body = json.loads(b"".join(chunks))
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):
            return None
        return body if isinstance(body, dict) else None

    async def session(self, request: Request) -> Response:
        """A participant's id, token and the items left."""
        try:
            body = await self._json(request)
        except _BodyTooLarge:
            return _too_large()
        if body is None:
            return JSONResponse({"error": "the body is not a JSON object"}, status_code=400)
        wanted, token = body.get("participant"), body.get("token")
        source = str(body.get("source") or "participant")[:MAX_TEXT]
        if wanted is not None and (not isinstance(wanted, str) or not 0 < len(wanted) <= 200):
            return JSONResponse({"error": "participant: expected an id"}, status_code=400)
        if wanted and token:
            if not self.store.token_ok(wanted, str(token)):
                self.store.refuse(wanted, None, None, "session: wrong token")
                return JSONResponse({"error": "participant: wrong token"}, status_code=403)
        elif wanted and wanted.startswith("p-"):  # ids the server assigned need the token
            return JSONResponse(
                {"error": "participant: an assigned id needs its token"}, status_code=403
            )
        pid, token = self.store.participant(wanted or None, source if wanted else "assigned")
        done = set(self.store.answered(pid))
        order = [i for i in participant_order(self.study, pid) if i not in done]
        study = self.study
        titles = dict(study.frameworks)
        items = [
            public_item(self.items[i], self.pictures[i], study.action_names.get(self.items[i].task))
            for i in order
        ]
        return JSONResponse(
            {
                "participant": pid,
                "token": token,
                "mode": study.mode,
                "question": study.question,
                "rating_question": study.rating_question,
                "rating_points": study.rating_points,
                "clarity_points": study.clarity_points,
                "frameworks": [
                    [name, titles.get(name, "none of these / other")]
                    for name in study.framework_names()
                ],
                "no_reason": NO_REASON,
                "no_framework": NO_FRAMEWORK,
                "total": len(self.items),
                "answered": len(done),
                "items": items,
            }
        )

    async def answer(self, request: Request) -> Response:
        """Store one answer at once, or refuse it (the reason is kept)."""
        try:
            body = await self._json(request)
        except _BodyTooLarge:
            self.store.refuse(None, None, None, "answer: body too large")
            return _too_large()
        if body is None:
            self.store.refuse(None, None, None, "answer: not a JSON object")
            return JSONResponse({"error": "the body is not a JSON object"}, status_code=400)
        pid, token = body.get("participant"), body.get("token")
        item_id, choice, ms = body.get("item"), body.get("choice"), body.get("ms")
        shown = self.items.get(item_id) if isinstance(item_id, str) else None
        expert = shown is not None and shown.kind == "expert"
        texts = (
            (pid, token, item_id) if expert and choice is None else (pid, token, item_id, choice)
        )
        if not all(isinstance(x, str) and 0 < len(x) <= MAX_TEXT for x in texts):
            self.store.refuse(None, None, None, "answer: missing or malformed field")
            return JSONResponse(
                {"error": "participant, token, item, choice: expected short strings"},
                status_code=400,
            )
        if not self.store.token_ok(pid, token):
            self.store.refuse(pid, item_id, choice, "wrong token")
            return JSONResponse({"error": "participant: wrong token"}, status_code=403)
        item = self.items.get(item_id)
        if item is None:
            self.store.refuse(pid, item_id, choice, "unknown item")
            return JSONResponse({"error": f"item: unknown {item_id!r}"}, status_code=400)
        if item.kind == "expert":
            return self._expert_answer(body, item, pid, ms)
        option = next((o for o in item.options if o.label == choice), None)
        if option is None:
            self.store.refuse(pid, item_id, choice, "unknown choice")
            return JSONResponse({"error": "choice: expected 'A' or 'B'"}, status_code=400)
        if not _is_time(ms):
            self.store.refuse(pid, item_id, choice, "bad time")
            return JSONResponse({"error": "ms: expected a time in ms"}, status_code=400)
        ratings = body.get("ratings")
        problem = rating_problem(ratings, item, self.study.rating_points)
        if problem is not None:
            self.store.refuse(pid, item_id, choice, problem)
            return JSONResponse(
                {"error": f"ratings: {problem}; expected {{'A': r, 'B': r}}, r an integer "
                          f"from 1 to {self.study.rating_points}"},
                status_code=400,
            )  # fmt: skip
        correct = None if item.expected is None else int(choice == item.expected)
        answer = Answer(
            pid, item_id, choice, option.variant, correct, float(ms), time.time(),
            rating_a=ratings["A"], rating_b=ratings["B"],
        )  # fmt: skip
        if not self.store.add(answer):
            self.store.refuse(pid, item_id, choice, "already answered")
            return JSONResponse({"error": f"item {item_id}: already answered"}, status_code=409)
        return JSONResponse({"stored": True})

    def _expert_answer(self, body: dict[str, Any], item: Item, pid: str, ms: Any) -> Response:
        """Store an expert's judgements of a state, or refuse them (the reason is kept)."""
        if not _is_time(ms):
            self.store.refuse(pid, item.id, None, "bad time")
            return JSONResponse({"error": "ms: expected a time in ms"}, status_code=400)
        problem = expert_problem(body, item, self.study)
        if problem is not None:
            self.store.refuse(pid, item.id, None, problem)
            return JSONResponse(
                {"error": f"{problem}; expected 'actions': one {{'acceptable': true|false, "
                          f"'framework': one of {self.study.framework_names()}}} per action, "
                          f"'clarity': 1 to {self.study.clarity_points} (null where the "
                          "panel stated no reason)"},
                status_code=400,
            )  # fmt: skip
        judgements = tuple(
            Judgement(a, bool(j["acceptable"]), str(j["framework"]))
            for a, j in enumerate(body["actions"])
        )
        answer = ExpertAnswer(pid, item.id, body.get("clarity"), judgements, float(ms), time.time())
        if not self.store.add_expert(answer):
            self.store.refuse(pid, item.id, None, "already answered")
            return JSONResponse({"error": f"item {item.id}: already answered"}, status_code=409)
        return JSONResponse({"stored": True})


def make_app(folder: Path) -> Starlette:
    """The ASGI application of a study folder.

    Raises:
        StudyError: The folder holds no study, or one of its files is refused
            (:class:`StudyApp`).

    """
    return StudyApp(folder).app


def serve(folder: Path, host: str = "127.0.0.1", port: int = 8765) -> None:
    """Serve a study until interrupted (uvicorn, one process).

    Raises:
        StudyError: The folder holds no study, or one of its files is refused
            (:class:`StudyApp`).

    """
    import uvicorn

    if not (Path(folder) / "study.json").is_file():
        raise StudyError(f"{folder}: no study.json; build it with 'amuled study build'")
    uvicorn.run(make_app(folder), host=host, port=int(port), log_level="warning")
