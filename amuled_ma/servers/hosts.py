"""Ollama server addresses and the one preflight (`preflight`): a server answers and has a model.

A missing server or model is one error up front, never a retry loop later.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from amuled_ma.errors import BackendUnavailable, ModelNotFound, ScenarioError
from amuled_ma.servers.urls import DEFAULT_PORT, normalize_host, normalize_hosts

if TYPE_CHECKING:
    import httpx

#: Address of a user's own Ollama server (the Ollama default).
DEFAULT_HOST = f"http://127.0.0.1:{DEFAULT_PORT}"
#: Name under which ``amuled ollama up --tiny`` registers the tiny SmolLM2 test model.
TINY_MODEL = "amuled-tiny"


def resolve_host(host: str | None = None) -> str:
    """Return the server URL: ``host``, else ``$OLLAMA_HOST``, else the default.

    ``HOST`` and ``HOST:PORT`` forms get a scheme and the default port 11434.

    Raises:
        ScenarioError: The address is malformed (`normalize_host`).
    """
    if host:
        return normalize_host(host)
    if os.environ.get("OLLAMA_HOST"):
        return normalize_host(os.environ["OLLAMA_HOST"], where="$OLLAMA_HOST")
    return DEFAULT_HOST


def pool_hosts(host: str | None, hosts: Sequence[str] | None) -> tuple[str, ...]:
    """The server URLs of a source: ``hosts`` (a pool), else ``host`` resolved.

    Args:
        host: One server (default ``$OLLAMA_HOST``, then ``http://127.0.0.1:11434``).
        hosts: A pool of servers, instead of ``host``.

    Returns:
        The normalised URLs, in the order given.

    Raises:
        ScenarioError: Both given, an empty list, a string instead of a list, a
            malformed address or the same server twice.

    """
    if hosts is None:
        return (resolve_host(host),)
    if host:
        raise ScenarioError(
            f"ollama: host {host!r} and hosts {list(hosts)!r} are both given; give one "
            "server with host, or a pool with hosts = [...] (list the host there too)"
        )
    return normalize_hosts(hosts, where="ollama hosts")


@dataclass(frozen=True)
class ServerCheck:
    """What :func:`preflight` found at a server.

    Attributes:
        host: The server's URL (normalised).
        version: The version the server reports.
        models: The names of the models it has (``/api/tags``).
        digest: The digest of the model asked for (``""`` when the server gives none;
            ``None`` when no model was asked for).

    """

    host: str
    version: str
    models: tuple[str, ...]
    digest: str | None = None


def up_command(model: str | None) -> str:
    """``amuled ollama up --tiny`` for :data:`TINY_MODEL` (any tag), else ``amuled ollama up``."""
    tiny = model is not None and model.split(":", 1)[0] == TINY_MODEL
    return "amuled ollama up --tiny" if tiny else "amuled ollama up"


def unreachable_error(
    host: str, error: BaseException | None = None, model: str | None = None
) -> BackendUnavailable:
    """The error of a server that does not answer: the host, the cause and how to start one.

    Args:
        host: The server's URL.
        error: What the request raised, if anything.
        model: The model the caller wanted; for :data:`TINY_MODEL` the advice is
            ``'amuled ollama up --tiny'``.

    Returns:
        The error to raise.

    """
    why = f" ({type(error).__name__}: {error})" if error is not None else ""
    up = up_command(model)
    return BackendUnavailable(
        f"no Ollama server answers at {host}{why}; start one with '{up}' "
        "(a private server; it prints its host) or 'ollama serve', or point OLLAMA_HOST "
        "(or the scenario's host) at a running server"
    )


def model_create_hint(model: str) -> str:
    """Return the command that makes ``model`` available on a server.

    Args:
        model: The model name.

    Returns:
        ``'amuled ollama up --tiny'`` for :data:`TINY_MODEL`, else ``'ollama pull MODEL'``
        (each with its ``ollama create`` alternative).

    """
    if model.split(":", 1)[0] == TINY_MODEL:
        return f"'amuled ollama up --tiny' (or 'ollama create {TINY_MODEL} -f Modelfile')"
    return f"'ollama pull {model}' (or 'ollama create {model} -f Modelfile' for a local file)"


def model_missing_error(
    model: str, host: str, available: Sequence[str] | None = None
) -> ModelNotFound:
    """The error of a model a server lacks: the model, the host, what it has, the fix.

    Args:
        model: The model asked for.
        host: The server's URL.
        available: The models the server has, when known.

    Returns:
        The error to raise.

    """
    has = f" (it has: {', '.join(available) or 'no models'})" if available is not None else ""
    return ModelNotFound(
        f"model {model!r} is not on the Ollama server at {host}{has}; make it available "
        f"with {model_create_hint(model)}"
    )


def preflight(
    host: str,
    model: str | None = None,
    timeout: float = 5.0,
    *,
    transport: httpx.BaseTransport | None = None,
) -> ServerCheck:
    """Check, within ``timeout`` seconds, that a server answers at ``host`` and has ``model``.

    Asks ``/api/version`` and ``/api/tags`` over one connection. Call it before a run so
    that a missing server or model is one clear error up front instead of a retry loop
    later.

    Args:
        host: Server address (any form :func:`normalize_host` accepts).
        model: Model to look for (``NAME`` means ``NAME:latest``); ``None`` checks the
            server only.
        timeout: Total seconds allowed for the checks.
        transport: An ``httpx`` transport (tests use ``httpx.MockTransport``).

    Returns:
        What was found: version, models and the model's digest.

    Raises:
        BackendUnavailable: The server does not answer; names the host and how to start one.
        ModelNotFound: The server lacks the model; names it, what the server has and the
            command that makes it available.
        ScenarioError: The address is malformed.

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
