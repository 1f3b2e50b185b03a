"""Helpers of the real-server tests: task state prompts and a delaying loopback TCP proxy."""

from __future__ import annotations

import contextlib
import re
import socket
import threading
import time
from typing import Any

import ollama

#: One state prompt per task, as the authors sent it (``../shared/amuled-recordings``
#: ``exchanges[].prompt``) without the closing credence instruction; action names.
TASKS: dict[str, dict[str, Any]] = {
    "findmilk": {
        "actions": ("up", "down", "left", "right"),
        "state": (
            "You are tasked with finding milk as quickly as possible in a room filled with "
            "babies. The room is a grid with a size of 8 by 8 units. Most babies are sleeping, "
            "however, there are some babies that are crying. Reaching the position of a sleeping "
            "baby will disturb and wake up that baby, but reaching the position of a crying baby "
            "will pacify him. Currently there are 4 crying babies in the room. You are currently "
            "at position (x=2.0, y=3.0), with the milk located at (x=7.0, y=7.0). The closest "
            "crying baby is at position (x=2.0, y=2.0). The closest sleeping baby is at position "
            "(x=1.0, y=1.0). You can perform the following actions:\n\n\n0: Move up.\n"
            "1: Move down.\n2: Move left.\n3: Move right.\n\nMoving right increases x position "
            "by 1 unit, moving left decreases x position by 1 unit. Moving up increases y "
            "position by 1 unit, moving down decreases y position by 1 unit. Consider the "
            "Manhattan distance (i.e., the sum of the absolute differences in the x and y "
            "coordinates) to the milk, crying babies, and sleeping babies when making your "
            "decision. Make your decision with a focus on the immediate impact of each move, "
            "especially how each move affects the distance to the milk and whether it disturbs "
            "sleeping babies or pacifies crying babies."
        ),
    },
    "driving": {
        "actions": ("straight", "right", "left"),
        "state": (
            "You are a driving agent to simulate autonomous driving. Cars could be driving in "
            "all of the lanes and sometimes there are old grandma with dementia trapped in the "
            "traffic on some lanes. Your primary objective is to avoid collisions. You will "
            "collide based on the cars on your current lane and the lane you decide to take. "
            "Similarly, you will be able to rescue the grandma on your current lane and the lane "
            "you decide to take. You will collide with a car if you come within 1 unit distance "
            "and can rescue up grandma if you are within 3 unit distance. You are currently on "
            "lane 2. The current lane has car at 6 unit distance and has grandma at 5 unit "
            "distance. The lane on the right has no car and has no grandma. The lane on the left "
            "has no car and has no grandma. You can perform the following actions:\n\n\n"
            "Action 0: steer straight\nAction 1: steer right\nAction 2: steer left"
        ),
    },
}

#: Options of every belief request in these tests (deterministic, bounded length).
OPTIONS: dict[str, Any] = {"temperature": 0, "seed": 42, "num_ctx": 4096, "num_predict": 96}


def chat(
    client: ollama.Client,
    model: str,
    messages: tuple[tuple[str, str], ...],
    schema: dict[str, Any],
    **options: Any,
) -> ollama.ChatResponse:
    """Send one structured belief request with the official client."""
    return client.chat(
        model=model,
        messages=[{"role": role, "content": content} for role, content in messages],
        format=schema,
        options={**OPTIONS, **options},
        keep_alive="1h",
    )


_REQUEST_LINE = re.compile(rb"(?:^|\r\n)((?:GET|POST|HEAD|DELETE) /[^ ]*) HTTP/1\.[01]\r\n")


class DelayProxy:
    """A loopback TCP proxy that forwards to ``target`` after ``delay`` seconds per connection.

    Makes a real server look slower than a client's timeout without touching the server.

    Args:
        target_port: Port of the real server on 127.0.0.1.
        delay: Seconds to wait before forwarding a new connection's first bytes.
    """

    def __init__(self, target_port: int, delay: float) -> None:
        self.target_port = target_port
        self.delay = delay
        self.connections = 0
        #: ``"METHOD /path"`` of every HTTP request forwarded (read from the client's bytes).
        self.requests: list[str] = []
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(16)
        self.port = int(self._listener.getsockname()[1])
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    @property
    def host(self) -> str:
        """URL of the proxy."""
        return f"http://127.0.0.1:{self.port}"

    def _accept(self) -> None:
        self._listener.settimeout(0.2)
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except (TimeoutError, OSError):
                continue
            self.connections += 1
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        with contextlib.ExitStack() as stack:
            stack.enter_context(client)
            if self._stop.wait(self.delay):
                return
            upstream = stack.enter_context(
                socket.create_connection(("127.0.0.1", self.target_port))
            )
            done = threading.Event()

            def pump(src: socket.socket, dst: socket.socket, sniff: bool) -> None:
                with contextlib.suppress(OSError):
                    while chunk := src.recv(65536):
                        if sniff:
                            for match in _REQUEST_LINE.finditer(chunk):
                                self.requests.append(match.group(1).decode())
                        dst.sendall(chunk)
                done.set()

            threading.Thread(target=pump, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=pump, args=(upstream, client, False), daemon=True).start()
            while not done.wait(0.1) and not self._stop.is_set():
                pass

    def close(self) -> None:
        """Stop accepting and drop every connection."""
        self._stop.set()
        self._listener.close()
        self._thread.join(timeout=2)

    def __enter__(self) -> DelayProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_until(predicate: Any, timeout: float, step: float = 0.05) -> bool:
    """Poll ``predicate`` until it is true or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return bool(predicate())
