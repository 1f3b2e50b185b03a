"""Ollama server addresses and the one preflight (`preflight`): a server answers and has a model."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from amuled_ma.errors import BackendUnavailable, ModelNotFound
from amuled_ma.servers.urls import DEFAULT_PORT, normalize_host

if TYPE_CHECKING:
    import httpx

#: Address of a user's own Ollama server (the Ollama default).
DEFAULT_HOST = f"http://127.0.0.1:{DEFAULT_PORT}"
#: Name under which ``amuled ollama up --tiny`` registers the tiny SmolLM2 test model.
TINY_MODEL = "amuled-tiny"


def resolve_host(host: str | None = None) -> str:
    """The server URL (`normalize_host`, which raises): ``host``, ``$OLLAMA_HOST``, the default."""
    if host:
        return normalize_host(host)
    if os.environ.get("OLLAMA_HOST"):
        return normalize_host(os.environ["OLLAMA_HOST"], where="$OLLAMA_HOST")
    return DEFAULT_HOST


@dataclass(frozen=True)
class ServerCheck:
    """What :func:`preflight` found at a server."""

    host: str
    version: str
    models: tuple[str, ...]  # ``/api/tags``
    digest: str | None = None  # of the model asked for ("": none given; None: none asked)


def up_command(model: str | None) -> str:
    """``amuled ollama up --tiny`` for :data:`TINY_MODEL` (any tag), else ``amuled ollama up``."""
    tiny = model is not None and model.split(":", 1)[0] == TINY_MODEL
    return "amuled ollama up --tiny" if tiny else "amuled ollama up"


def unreachable_error(
    host: str, error: BaseException | None = None, model: str | None = None
) -> BackendUnavailable:
    """The error of a server that does not answer: the host, the cause and how to start one."""
    why = f" ({type(error).__name__}: {error})" if error is not None else ""
    up = up_command(model)
    return BackendUnavailable(
        f"no Ollama server answers at {host}{why}; start one with '{up}' "
        "(a private server; it prints its host) or 'ollama serve', or point OLLAMA_HOST "
        "(or the scenario's host) at a running server"
    )


def model_missing_error(
    model: str, host: str, available: Sequence[str] | None = None
) -> ModelNotFound:
    """The error of a model a server lacks: the model, the host, what it has, the fix."""
    has = f" (it has: {', '.join(available) or 'no models'})" if available is not None else ""
    how = f"'ollama pull {model}' (or 'ollama create {model} -f Modelfile' for a local file)"
    if model.split(":", 1)[0] == TINY_MODEL:
        how = f"'amuled ollama up --tiny' (or 'ollama create {TINY_MODEL} -f Modelfile')"
    return ModelNotFound(
        f"model {model!r} is not on the Ollama server at {host}{has}; make it available with {how}"
    )


def preflight(
    host: str,
    model: str | None = None,
    timeout: float = 5.0,
    *,
    transport: httpx.BaseTransport | None = None,
) -> ServerCheck:
    """Check within ``timeout`` s that ``host`` answers and has ``model`` (``NAME``: ``:latest``).

    Asks ``/api/version`` and ``/api/tags`` over one connection; ``model`` None: the server only.
    `BackendUnavailable`: no answer; `ModelNotFound`: no model; `ScenarioError`: a bad address.
    """
    import httpx  # here: parsing a host needs no HTTP client

    url = normalize_host(host)
    deadline = time.monotonic() + timeout
    try:
        with httpx.Client(transport=transport, timeout=timeout) as client:
            reply = client.get(f"{url}/api/version")
            reply.raise_for_status()
            version = str(reply.json().get("version", "unknown"))
            left = max(0.5, deadline - time.monotonic())
            reply = client.get(f"{url}/api/tags", timeout=left)
            reply.raise_for_status()
            listing = reply.json().get("models") or []
            models = tuple(str(m.get("name") or m.get("model")) for m in listing)
    except (httpx.HTTPError, ValueError, AttributeError) as error:  # not an Ollama reply
        raise unreachable_error(url, error, model) from error
    if model is None:
        return ServerCheck(url, version, models)
    wanted = {model, model if ":" in model else f"{model}:latest"}
    for entry, name in zip(listing, models, strict=True):
        if name in wanted or str(entry.get("model")) in wanted:
            return ServerCheck(url, version, models, str(entry.get("digest") or ""))
    raise model_missing_error(model, url, models)
