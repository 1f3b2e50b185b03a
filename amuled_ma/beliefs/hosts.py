"""Ollama server addresses: one parser for every place a host is given.

A host comes from ``[feedback].host``, ``--host``, ``$OLLAMA_HOST`` or ``amuled ollama``;
``HOST``, ``HOST:PORT`` and ``http(s)://HOST:PORT`` forms are accepted, the scheme
defaults to ``http`` and the port to 11434 (443 for ``https``). A malformed address (no
host, a port that is not a number in 1..65535, another scheme) is refused before any
request, naming where it came from and the fix.
"""

from __future__ import annotations

import urllib.parse

from amuled_ma.errors import ScenarioError

#: Port of an Ollama server when none is given.
DEFAULT_PORT = 11434


def normalize_host(host: str, *, where: str = "Ollama host") -> str:
    """Return ``host`` as ``scheme://host:port`` (no trailing slash), checked.

    Args:
        host: ``HOST``, ``HOST:PORT`` or a full ``http(s)://HOST:PORT[/path]`` URL.
        where: Where the value came from, for the error message.

    Returns:
        The URL with scheme and port.

    Raises:
        ScenarioError: No host name, a scheme other than http(s), or a bad port.

    """
    raw = host.strip().rstrip("/")
    text = raw if "://" in raw else "http://" + raw
    parts = urllib.parse.urlsplit(text)
    example = "e.g. http://127.0.0.1:11434"
    if parts.scheme not in ("http", "https"):
        raise ScenarioError(
            f"{where} {host!r}: scheme {parts.scheme!r} is not http or https ({example})"
        )
    try:
        port = parts.port
    except ValueError:
        port_text = parts.netloc.rsplit(":", 1)[-1]
        raise ScenarioError(
            f"{where} {host!r}: the port {port_text!r} is not a number in 1..65535 ({example})"
        ) from None
    if not parts.hostname:
        raise ScenarioError(f"{where} {host!r}: no host name ({example})")
    if port is None:
        port = 443 if parts.scheme == "https" else DEFAULT_PORT
    elif not 1 <= port <= 65535:
        raise ScenarioError(f"{where} {host!r}: port {port} is outside 1..65535 ({example})")
    name = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    return f"{parts.scheme}://{name}:{port}{parts.path}".rstrip("/")
