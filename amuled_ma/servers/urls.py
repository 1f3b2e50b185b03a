"""An LLM server's URL parsed once: ``HOST``, ``HOST:PORT``, ``http(s)://HOST:PORT``."""

from __future__ import annotations

import urllib.parse
from collections.abc import Sequence

from amuled_ma.errors import ScenarioError

#: Port of an Ollama server when none is given.
DEFAULT_PORT = 11434


def normalize_host(host: str, *, where: str = "Ollama host") -> str:
    """Return ``host`` (``HOST[:PORT]``, ``http(s)://HOST:PORT[/path]``) as ``scheme://host:port``.

    `ScenarioError` naming ``where``: no host name, a scheme other than http(s), or a bad port.
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


def normalize_hosts(hosts: object, *, where: str = "Ollama hosts") -> tuple[str, ...]:
    """Return a pool's list of server addresses, each normalised by :func:`normalize_host`.

    `ScenarioError`: not a list of strings, empty, a bad address, or a server twice (normalised).
    """
    example = 'hosts = ["http://gpu1:11434", "http://gpu2:11434"]'
    if isinstance(hosts, str | bytes) or not isinstance(hosts, Sequence):
        raise ScenarioError(
            f"{where} expects a list of server URLs, found {hosts!r}; write {example}"
        )
    if not hosts:
        raise ScenarioError(
            f"{where} expects at least one server URL, found an empty list; list the "
            f"servers ({example}), or give one host instead"
        )
    urls: list[str] = []
    for i, entry in enumerate(hosts):
        if not isinstance(entry, str):
            raise ScenarioError(f"{where}[{i}] expects a server URL, found {entry!r} ({example})")
        url = normalize_host(entry, where=f"{where}[{i}]")
        if url in urls:
            raise ScenarioError(
                f"{where}[{i}] {entry!r} is {url}, the same server as item "
                f"[{urls.index(url)}] ({hosts[urls.index(url)]!r}); list each server once"
            )
        urls.append(url)
    return tuple(urls)
