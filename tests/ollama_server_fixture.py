"""Session fixtures for ``@pytest.mark.ollama`` tests: a real Ollama server with the tiny model.

``ollama_host`` gives the URL of a server that has :data:`TEST_MODEL`:

1. ``$OLLAMA_HOST`` when it is set, answers within 5 s and has the model (e.g. after
   ``export OLLAMA_HOST=$(amuled ollama up --tiny)``);
2. otherwise a private server started once per session from the ``ollama`` binary
   (``PATH``, ``$AMULED_OLLAMA_BIN`` or ``.ci/setup-ollama``'s cache), with the tiny model
   registered from the SmolLM2 GGUF, stopped at the end of the session.

``OLLAMA_HOST`` is set to that URL for the session. When neither works, the tests skip
with the reason, except in CI (``CI=true``), where they FAIL: CI must really run them.

Use from a conftest: ``from ollama_server_fixture import *  # noqa: F403``.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator

import httpx
import pytest

from amuled_ma.errors import AmuledError
from amuled_ma.servers import local_server as llm_server
from amuled_ma.servers.hosts import preflight

#: Model the ``ollama`` tests use (``$AMULED_TEST_MODEL`` overrides it).
TEST_MODEL = os.environ.get("AMULED_TEST_MODEL", llm_server.TINY_MODEL)

__all__ = [
    "TEST_MODEL",
    "in_ci",
    "ollama_host",
    "ollama_model",
    "private_ollama_server",
    "start_private_server",
    "warm_up",
]


def in_ci() -> bool:
    """Return True when running under CI (``CI`` set to true/1/yes)."""
    return os.environ.get("CI", "").strip().lower() in {"true", "1", "yes"}


def _unavailable(reason: str) -> None:
    message = f"no Ollama server for the 'ollama' tests: {reason}"
    if in_ci():
        pytest.fail(f"{message} (CI=true: these tests must run; run .ci/setup-ollama)")
    pytest.skip(message)


def warm_up(host: str, model: str, timeout: float = 120.0) -> None:
    """Load ``model`` into the server's memory so the first test does not pay for it."""
    reply = httpx.post(
        f"{llm_server.normalize_host(host)}/api/generate",
        json={"model": model, "prompt": "", "keep_alive": "1h"},
        timeout=timeout,
    )
    reply.raise_for_status()


def start_private_server(
    workdir: str | os.PathLike[str] | None = None, **kwargs: object
) -> llm_server.OllamaServer:
    """Start a private server with the tiny model registered (caller stops it).

    Args:
        workdir: Directory for the server's files (default: a temporary one).
        **kwargs: More :class:`~amuled_ma.servers.local_server.OllamaServer` arguments.

    Returns:
        The running server.
    """
    server = llm_server.OllamaServer(workdir=workdir, **kwargs)  # type: ignore[arg-type]
    server.start()
    try:
        server.create_model(
            llm_server.TINY_MODEL, llm_server.find_tiny_gguf(), llm_server.TINY_PARAMETERS
        )
    except BaseException:
        server.stop()
        raise
    return server


@pytest.fixture(scope="session")
def ollama_host() -> Iterator[str]:
    """URL of a real Ollama server with :data:`TEST_MODEL`; sets ``OLLAMA_HOST`` for the session."""
    existing = os.environ.get("OLLAMA_HOST")
    server: llm_server.OllamaServer | None = None
    host: str | None = None
    if existing:
        try:
            preflight(existing, TEST_MODEL, timeout=5.0)
            host = llm_server.normalize_host(existing)
        except AmuledError:
            host = None  # not answering or lacks the model: start our own below
    if host is None:
        if TEST_MODEL != llm_server.TINY_MODEL:
            _unavailable(f"AMULED_TEST_MODEL={TEST_MODEL} needs OLLAMA_HOST at a server with it")
        try:
            server = start_private_server()
        except AmuledError as error:
            _unavailable(str(error))
        assert server is not None
        host = server.host
    try:
        warm_up(host, TEST_MODEL)
        with pytest.MonkeyPatch.context() as patch:
            patch.setenv("OLLAMA_HOST", host)
            yield host
    finally:
        if server is not None:
            server.stop()


@pytest.fixture(scope="session")
def ollama_model(ollama_host: str) -> str:
    """Name of the model to use on ``ollama_host``."""
    return TEST_MODEL


@pytest.fixture
def private_ollama_server(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[Callable[..., llm_server.OllamaServer]]:
    """Factory of extra private servers (with the tiny model) for fault tests; stops them all.

    Skips (fails in CI) when no binary or model exists.
    """
    started: list[llm_server.OllamaServer] = []

    def make(**kwargs: object) -> llm_server.OllamaServer:
        try:
            server = start_private_server(tmp_path_factory.mktemp("ollama"), **kwargs)
        except AmuledError as error:
            _unavailable(str(error))
            raise
        started.append(server)
        return server

    yield make
    for server in started:
        server.stop()
        shutil.rmtree(server.workdir, ignore_errors=True)  # ~100 MB of model blobs each
