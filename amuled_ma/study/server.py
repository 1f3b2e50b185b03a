"""``amuled study serve``: the participant page and its answer API (Starlette; docs/study.md)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import ipaddress
import re
import socket
import sys
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import numpy as np
from pydantic import ValidationError
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
    NotInFolder,
    Study,
    StudyError,
    public_item,
    read_folder_file,
    read_study,
)
from amuled_ma.study.requests import (
    AnswerEnvelope,
    ExpertAnswerRequest,
    PairAnswer,
    SessionRequest,
    answer_models,
    first_error,
    refusal_reason,
    where,
)

STATIC = Path(__file__).parent / "static"
#: The consent page templates ``amuled study build`` writes into a study folder.
TEMPLATES = Path(__file__).parent / "templates"
#: Largest state picture read [bytes] (a drawn state is about 3 KB).
MAX_PICTURE_BYTES = 4 * 2**20
#: Largest consent page read [bytes] (templates are about 2 KB; room for inlined pictures).
MAX_CONSENT_BYTES = 16 * 2**20
#: Largest request body read [bytes] (an answer is under 1 KB); a longer one gets 413.
MAX_BODY_BYTES = 64 * 2**10
#: What the page shows without a consent file.
NO_CONSENT = "<p>(no consent page)</p>"
#: What a participant is shown when the consent file is refused (the reason goes to stderr).
CONSENT_REFUSED = "<p>(the consent page cannot be shown; please tell the researcher)</p>"


class _BodyTooLarge(Exception):
    """A request body over `MAX_BODY_BYTES` (answered 413, not read further)."""


def _refused(status: int, error: str) -> JSONResponse:
    """A refused request with its one-line reason."""
    return JSONResponse({"error": error}, status_code=status)


#: The reply to a body over `MAX_BODY_BYTES`.
TOO_LARGE = f"the body is more than the {MAX_BODY_BYTES:,} bytes an answer may be"


def _said(error: ValidationError) -> str:
    """A validation error as a reply's short reason: ``ratings.A: Input should be ...``."""
    loc, _, message = first_error(error)
    return f"{where(loc)}: {message}"


def placeholders(text: str) -> list[str]:
    """The shipped consent templates' ``[...]`` placeholders that ``text`` still holds."""
    found: set[str] = set()
    for template in sorted(TEMPLATES.glob("*.html")):
        found.update(" ".join(p.split()) for p in re.findall(r"\[[^\[\]]+\]", template.read_text()))
    flat = " ".join(text.split())
    return [p for p in sorted(found) if p in flat]


def participant_order(study: Study, participant: str) -> list[str]:
    """The item ids in the order this participant sees them (seed and id decide it)."""
    digest = hashlib.sha256(f"{study.seed}:{participant}".encode()).digest()
    rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))
    ids = [item.id for item in study.items]
    return [ids[i] for i in rng.permutation(len(ids)).tolist()]


class StudyApp:
    """The server's state; StudyError for a folder file refused or a placeholder consent page."""

    def __init__(self, folder: Path, *, allow_placeholder_consent: bool = False) -> None:
        self.folder = Path(folder)
        self.study = read_study(self.folder)
        self.pictures = {
            item.id: read_folder_file(
                self.folder,
                item.picture,
                MAX_PICTURE_BYTES,
                "state picture",
                note="a drawn state is about 3 KB",
                fix="is it the right folder? Rebuild the study with 'amuled study build'",
            )
            for item in self.study.items
        }
        consent = self.consent_text()  # an unreadable consent page stops the start
        left = placeholders(consent)
        if left and not allow_placeholder_consent:
            raise StudyError(
                f"{self.folder / CONSENT_FILE}: the consent page still holds the template's "
                f"placeholders {', '.join(left)}; write the study's own text there, or pass "
                "--allow-placeholder-consent to serve it as it is (a trial run)"
            )
        self.items = {item.id: item for item in self.study.items}
        self.pair_model, self.expert_model = answer_models(
            self.study.rating_points, self.study.clarity_points, self.study.framework_names()
        )
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
        """The study folder's ``consent.html`` (`NO_CONSENT` without one), by `read_folder_file`."""
        path = self.folder / CONSENT_FILE
        if not path.exists() and not path.is_symlink():
            return NO_CONSENT
        return read_folder_file(
            self.folder,
            CONSENT_FILE,
            MAX_CONSENT_BYTES,
            "consent page",
            note="the shipped templates are about 2 KB",
            fix="is it the right file? Edit it down, or rebuild the study to get the template",
        )

    async def consent(self, request: Request) -> Response:
        """The consent fragment; a refusal (404, 500) goes to stderr, never its path to the page."""
        try:
            return HTMLResponse(self.consent_text())
        except StudyError as refused:  # NotInFolder: as if there were none
            print(f"amuled study serve: {refused}", file=sys.stderr, flush=True)
            if isinstance(refused, NotInFolder):
                return HTMLResponse(NO_CONSENT, status_code=404)
            return HTMLResponse(CONSENT_REFUSED, status_code=500)

    async def health(self, request: Request) -> Response:
        """Whether the server is up, with its counts."""
        return JSONResponse({"ok": True, "items": len(self.items)})

    async def _body(self, request: Request) -> bytes:
        """The request's body; `_BodyTooLarge` (not read further) over `MAX_BODY_BYTES`."""
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
        return b"".join(chunks)

    async def session(self, request: Request) -> Response:
        """A participant's id, token and the items left, in the participant's own order."""
        try:
            body = SessionRequest.model_validate_json(await self._body(request))
        except _BodyTooLarge:
            return _refused(413, TOO_LARGE)
        except ValidationError as refused:
            return _refused(400, _said(refused))
        wanted, token = body.participant, body.token
        if wanted and token:
            if not self.store.token_ok(wanted, token):
                self.store.refuse(wanted, None, None, "session: wrong token")
                return _refused(403, "participant: wrong token")
        elif wanted and wanted.startswith("p-"):  # ids the server assigned need the token
            return _refused(403, "participant: an assigned id needs its token")
        source = body.source or "participant"
        pid, token = self.store.participant(wanted, source if wanted else "assigned")
        done = set(self.store.answered(pid))
        order = [i for i in participant_order(self.study, pid) if i not in done]
        study = self.study
        titles = dict(study.frameworks)
        items = [
            public_item(self.items[i], self.pictures[i], study.action_names.get(self.items[i].task))
            for i in order
        ]
        shown = {"mode", "question", "rating_question", "rating_points", "clarity_points"}
        return JSONResponse(
            {
                "participant": pid,
                "token": token,
                **study.model_dump(include=shown),
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
        """Store one answer (envelope, token, then the item's model checked), or refuse it."""
        try:
            envelope = AnswerEnvelope.model_validate_json(await self._body(request))
        except _BodyTooLarge:
            self.store.refuse(None, None, None, "answer: body too large")
            return _refused(413, TOO_LARGE)
        except ValidationError as refused:
            self.store.refuse(None, None, None, "answer: missing or malformed field")
            return _refused(
                400, f"{_said(refused)}; expected participant, token, item: short strings"
            )
        pid, item_id, choice = envelope.participant, envelope.item, envelope.choice
        if not self.store.token_ok(pid, envelope.token):
            self.store.refuse(pid, item_id, choice, "wrong token")
            return _refused(403, "participant: wrong token")
        item = self.items.get(item_id)
        if item is None:
            self.store.refuse(pid, item_id, choice, "unknown item")
            return _refused(400, f"item: unknown {item_id!r}")
        study = self.study
        model: type[PairAnswer | ExpertAnswerRequest]
        if item.kind == "expert":
            reasoned = item.panel is not None and item.panel.has_reasons()
            model = self.expert_model(len(study.action_names.get(item.task, [])), reasoned)
            choice = None
            expected = (
                "'ms': a time in ms, 'actions': one {'acceptable': true|false, 'framework': one "
                f"of {study.framework_names()}}} per action, 'clarity': 1 to "
                f"{study.clarity_points} (null where the panel stated no reason)"
            )
        else:
            model = self.pair_model
            expected = (
                "'choice': 'A' or 'B', 'ms': a time in ms, 'ratings': {'A': r, 'B': r}, r an "
                f"integer from 1 to {study.rating_points}"
            )
        try:
            form = model.model_validate(envelope.model_dump(exclude_unset=True))
        except ValidationError as refused:
            reason = refusal_reason(*first_error(refused)[:2])
            self.store.refuse(pid, item_id, choice, reason)
            return _refused(400, f"{reason} ({_said(refused)}); expected {expected}")
        if isinstance(form, ExpertAnswerRequest):
            judged = tuple(
                Judgement(a, j.acceptable, j.framework) for a, j in enumerate(form.actions)
            )
            expert = ExpertAnswer(pid, item_id, form.clarity, judged, float(form.ms), time.time())
            stored = self.store.add_expert(expert)
        else:
            variant = next(o.variant for o in item.options if o.label == form.choice)
            correct = None if item.expected is None else int(form.choice == item.expected)
            ratings = form.ratings
            stored = self.store.add(
                Answer(pid, item_id, form.choice, variant, correct, float(form.ms), time.time(),
                       rating_a=ratings.A, rating_b=ratings.B)
            )  # fmt: skip
        if not stored:
            self.store.refuse(pid, item_id, choice, "already answered")
            return _refused(409, f"item {item_id}: already answered")
        return JSONResponse({"stored": True})


def is_loopback(host: str) -> bool:
    """Whether ``host`` is this machine only: ``localhost`` or a loopback address."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_host(host: str, *, public: bool) -> None:
    """Refuse (StudyError) a non-loopback ``host`` (``""``, ``0.0.0.0`` too) unless ``public``."""
    if not public and not is_loopback(host):
        shown = host or repr(host)
        raise StudyError(
            f"--host {shown}: not a loopback address (it lets other machines reach the "
            "study); pass --public as well to serve it there, or leave --host out "
            "(127.0.0.1, this machine only)"
        )


def listen_socket(host: str, port: int) -> socket.socket:
    """The bound socket the study is served on; StudyError for an address or port refused."""
    try:
        infos = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
    except socket.gaierror as failure:
        raise StudyError(
            f"--host {host}: not an address of this machine ({failure.strerror}); give an "
            "address of one of its interfaces"
        ) from None
    family, kind, proto, _, address = infos[0]
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
    try:
        sock.bind(address)
    except OSError as failure:
        sock.close()
        if failure.errno == errno.EADDRINUSE:
            raise StudyError(
                f"--port {port}: port {port} of {host or 'every interface'} is in use "
                f"(another server, or this study served already?); pass a free one with "
                f"--port N (e.g. --port {port + 1 if port < 65535 else 8765})"
            ) from None
        raise StudyError(
            f"--host {host} --port {port}: cannot listen there ({failure.strerror}); pass "
            "another address or --port N"
        ) from None
    return sock


def serve(
    folder: Path,
    host: str = "127.0.0.1",
    port: int = 8765,
    *,
    public: bool = False,
    allow_placeholder_consent: bool = False,
    say: Callable[[str], None] = print,
) -> None:
    """Serve a study until interrupted (uvicorn); every refusal comes before ``say`` is told."""
    import uvicorn

    check_host(host, public=public)
    app = StudyApp(folder, allow_placeholder_consent=allow_placeholder_consent).app
    sock = listen_socket(host, port)
    if not is_loopback(host):
        print(
            f"amuled: warning: serving on {host or 'every interface'}: any machine that can "
            "reach this one can open the study and post answers",
            file=sys.stderr,
            flush=True,
        )
    say(f"study {folder}: serving on http://{host or '0.0.0.0'}:{port}/ (Ctrl-C stops)")
    with sock:
        uvicorn.Server(uvicorn.Config(app, log_level="warning")).run(sockets=[sock])
