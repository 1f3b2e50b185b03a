"""A long phase's progress: a tqdm bar, or a plain line after `FIRST_LINE_S`, every `PLAIN_EVERY_S`.

A watcher thread keeps both alive while one step takes long, and still while `held`.
"""

from __future__ import annotations

import contextlib
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import IO

#: A plain progress line, as `Progress.line` writes it (tools that read stderr skip these).
PLAIN_LINE = re.compile(r"^.+: [\d,]+/(?:[\d,]+|\?) \S+, .+ elapsed, ETA .+$")
#: Seconds a phase runs before its first plain line (a shorter phase prints none).
FIRST_LINE_S = 10.0
#: Longest silence between two plain lines [s].
PLAIN_EVERY_S = 30.0
#: Seconds between two redraws of a bar while no step finishes.
BAR_REFRESH_S = 1.0


_held = 0
_held_lock = threading.Lock()


@contextlib.contextmanager
def held() -> Iterator[None]:
    """Keep every bar and plain line still meanwhile (a person reads and types a question)."""
    global _held
    with _held_lock:
        _held += 1
    try:
        yield
    finally:
        with _held_lock:
            _held -= 1


def duration(seconds: float) -> str:
    """``42 s``, ``3 min 5 s``, ``2 h 4 min``: a duration people read at a glance."""
    seconds = max(0.0, seconds)
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, rest = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes} min {rest} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes} min"


class Progress:
    """The progress of one phase (``findmilk/amuled``): ``update`` each step, ``close`` at the end.

    ``total`` None: no ETA. ``bar``: a tqdm bar, else plain lines (after ``first`` s, then at
    most ``every`` s apart). ``initial``: steps done before (not in the ETA). ``watch=False``:
    no watcher thread (a test calls `check`).
    """

    def __init__(
        self,
        phase: str,
        total: int | None,
        *,
        bar: bool,
        initial: int = 0,
        unit: str = "it",
        first: float | None = None,
        every: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        stream: IO[str] | None = None,
        watch: bool = True,
    ) -> None:
        self.phase = phase
        self.total = total
        self.unit = unit
        self.done = initial
        self._initial = initial
        self._first = FIRST_LINE_S if first is None else first
        self._every = PLAIN_EVERY_S if every is None else every
        self._clock = clock
        self._stream = stream
        self._start = clock()
        self._last_line: float | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._bar = None
        if bar:
            from tqdm.auto import tqdm

            self._bar = tqdm(
                total=total,
                initial=initial,
                desc=phase,
                unit=unit,
                dynamic_ncols=True,
                leave=False,
                file=stream,
            )
        self._thread: threading.Thread | None = None
        if watch:
            self._thread = threading.Thread(target=self._watch, name="progress", daemon=True)
            self._thread.start()

    def update(self, n: int = 1) -> None:
        """Count ``n`` steps done; a plain line is written when one is due."""
        with self._lock:
            self.done += n
            if self._bar is not None:
                self._bar.update(n)
        self.check()

    def check(self) -> bool:
        """Write the plain line if it is due (the watcher calls this); True when written."""
        if self._bar is not None or _held:
            return False
        with self._lock:
            now = self._clock()
            since = now - (self._start if self._last_line is None else self._last_line)
            if since < (self._first if self._last_line is None else self._every):
                return False
            self._last_line = now
            stream = self._stream if self._stream is not None else sys.stderr
            stream.write(self.line(now) + "\n")
            stream.flush()
        return True

    def line(self, now: float | None = None) -> str:
        """``<phase>: <done>/<total> <unit>, <elapsed> elapsed, ETA <left>``."""
        now = self._clock() if now is None else now
        elapsed = now - self._start
        total = "?" if self.total is None else f"{self.total:,}"
        here = self.done - self._initial
        if self.total is None:
            eta = "not known"
        elif here <= 0:
            eta = "after the first step"
        else:
            eta = duration(elapsed / here * max(0, self.total - self.done))
        return (
            f"{self.phase}: {self.done:,}/{total} {self.unit}, {duration(elapsed)} elapsed, "
            f"ETA {eta}"
        )

    def _watch(self) -> None:
        plain = max(min(self._first, self._every) / 10, 0.01)
        wait = BAR_REFRESH_S if self._bar is not None else plain
        while not self._stop.wait(wait):
            if self._bar is not None:
                if not _held:
                    with self._lock:
                        self._bar.refresh()
            else:
                self.check()

    def close(self) -> None:
        """Stop the watcher and close the bar (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
