"""``amuled view --serve``: one HTML file at ``/`` and its own name, all else 404, unlogged."""

from __future__ import annotations

import http.server
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: Largest page served, held in memory [bytes] (3 MB for a 300-step Driving episode).
MAX_PAGE_BYTES = 64 * 2**20


class _OneFileHandler(http.server.BaseHTTPRequestHandler):
    """Serve one file at ``/`` (and its name); everything else is 404."""

    body: bytes = b""
    name: str = "index.html"

    def do_GET(self) -> None:
        """Answer the page, or 404."""
        if self.path.split("?", 1)[0] not in ("/", f"/{self.name}"):
            self.send_error(404, "only the viewer page is served here")
            return
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(self.body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(self.body)

    def log_message(self, format: str, *args: Any) -> None:
        """Stay quiet (the command prints the URL once)."""


def make_server(path: Path, host: str = "127.0.0.1", port: int = 0) -> http.server.HTTPServer:
    """An HTTP server for one file (read once, before binding); ``port`` 0 picks a free one.

    OSError: the file cannot be read or the address bound; AmuledError: over `MAX_PAGE_BYTES`.
    """
    from amuled_ma.files.limits import read_bounded_bytes

    body = read_bounded_bytes(
        path,
        MAX_PAGE_BYTES,
        "page",
        note="a viewer page is at most a few MB",
        fix="is it the right file? Open it in a browser from the file instead (its file:// URL)",
    )
    handler = type("ViewerHandler", (_OneFileHandler,), {"body": body, "name": Path(path).name})
    return http.server.ThreadingHTTPServer((host, port), handler)


def serve(
    path: Path,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    seconds: float | None = None,
    say: Callable[[str], None] = print,
) -> None:
    """Serve one page until Ctrl-C (or ``seconds``), telling ``say`` its URL (as `make_server`)."""
    server = make_server(path, host, port)
    say(f"serving {path} at http://{host}:{server.server_address[1]}/ (Ctrl-C stops)")
    if seconds is not None:
        timer = threading.Timer(seconds, server.shutdown)
        timer.daemon = True  # Ctrl-C before it fires does not wait for it
        timer.start()
    with server:
        server.serve_forever()
