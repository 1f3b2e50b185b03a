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
  already answered by that participant (409). Every refusal is kept with its reason.
- ``GET /api/health``: ``{"ok": true, "items": n}``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
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

    """

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.study = read_study(self.folder)
        self.pictures = {
            item.id: (self.folder / item.picture).read_text(encoding="utf-8")
            for item in self.study.items
        }
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

    async def consent(self, request: Request) -> Response:
        """The researcher's consent and instructions fragment."""
        path = self.folder / CONSENT_FILE
        text = path.read_text(encoding="utf-8") if path.is_file() else "<p>(no consent page)</p>"
        return HTMLResponse(text)

    async def health(self, request: Request) -> Response:
        """Whether the server is up, with its counts."""
        return JSONResponse({"ok": True, "items": len(self.items)})

    async def _json(self, request: Request) -> dict[str, Any] | None:
        try:
            body = json.loads(await request.body())
        except (json.JSONDecodeError, UnicodeDecodeError):
            return None
        return body if isinstance(body, dict) else None

    async def session(self, request: Request) -> Response:
        """A participant's id, token and the items left."""
        body = await self._json(request)
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
        body = await self._json(request)
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
        StudyError: The folder holds no study.

    """
    return StudyApp(folder).app


def serve(folder: Path, host: str = "127.0.0.1", port: int = 8765) -> None:
    """Serve a study until interrupted (uvicorn, one process).

    Raises:
        StudyError: The folder holds no study.

    """
    import uvicorn

    if not (Path(folder) / "study.json").is_file():
        raise StudyError(f"{folder}: no study.json; build it with 'amuled study build'")
    uvicorn.run(make_app(folder), host=host, port=int(port), log_level="warning")
