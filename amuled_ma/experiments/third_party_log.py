"""Third-party warnings and log records go to a log file, not a command's output."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: The environment variable naming the log file.
LOG_ENV = "AMULED_LOG"

#: The file handler of the command running now (None: no command line, leave logging be).
_HANDLER: logging.Handler | None = None
#: Ray's terminal handlers `ray_to_log` took away, given back after the command.
_RAY_HANDLERS: list[logging.Handler] = []


def log_path() -> Path:
    """The log file: ``$AMULED_LOG``, else ``<user data folder>/amuled.log``."""
    env = os.environ.get(LOG_ENV)
    if env:
        return Path(os.path.expanduser(env))
    from amuled_ma.scenario.paths import user_data_dir

    return user_data_dir() / "amuled.log"


class _LazyFileHandler(logging.FileHandler):
    """A file handler that makes the log's folder when it first writes."""

    def _open(self) -> Any:
        Path(self.baseFilename).parent.mkdir(parents=True, exist_ok=True)
        return super()._open()


@contextlib.contextmanager
def third_party_to_log(path: Path | None = None) -> Iterator[Path]:
    """Send warnings and third-party records to ``path`` for the block; yields that path."""
    global _HANDLER
    path = Path(path) if path is not None else log_path()
    handler = _LazyFileHandler(path, delay=True, encoding="utf-8")
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    warned = logging.getLogger("py.warnings")
    previous = (_HANDLER, root.level, warned.propagate)
    root.addHandler(handler)
    if root.level > logging.WARNING or root.level == logging.NOTSET:
        root.setLevel(logging.WARNING)
    logging.captureWarnings(True)
    _HANDLER = handler
    try:
        yield path
    finally:
        logging.captureWarnings(False)
        root.removeHandler(handler)
        _HANDLER, level, _ = previous
        root.setLevel(level)
        ray_logger = logging.getLogger("ray")
        if handler in ray_logger.handlers:
            ray_logger.removeHandler(handler)
        while _RAY_HANDLERS:  # Ray, used again in this process, prints as it did
            ray_logger.addHandler(_RAY_HANDLERS.pop())
        handler.close()


def ray_to_log() -> None:
    """Give Ray's logger the command's log; call after importing Ray, before ``ray.init``."""
    if _HANDLER is None:
        return
    ray_logger = logging.getLogger("ray")
    for handler in list(ray_logger.handlers):
        if type(handler).__name__ == "PlainRayHandler" or (
            isinstance(handler, logging.StreamHandler)
            and not isinstance(handler, logging.FileHandler)
        ):
            ray_logger.removeHandler(handler)
            _RAY_HANDLERS.append(handler)
    if _HANDLER not in ray_logger.handlers:
        ray_logger.addHandler(_HANDLER)
