"""The command line in the CLI-level tests: a tiny run's settings, and the real command.

:data:`TINY` (a few seconds) and :data:`RULES`; :func:`amuled` runs ``python -m amuled_ma``
in a subprocess, and :func:`one_line` checks that a failure printed one line, not a traceback.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from amuled_ma.monitor.progress import PLAIN_LINE

TINY = [
    "--set", "base.total_steps=1024",
    "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16",
    "--set", "finetune.iterations=3",
    "--set", "finetune.num_envs=4",
    "--set", "finetune.num_steps_per_env=8",
    "--set", "output.tensorboard=false",
    "--no-progress",
]  # fmt: skip
RULES = ["--set", 'feedback.source="rules"']
#: The checkout's root.
REPO = Path(__file__).resolve().parents[1]


def amuled(*args: str, cwd: Path = REPO, timeout: float = 300) -> subprocess.CompletedProcess:
    """The real command line, in a subprocess (its output captured as text)."""
    return subprocess.run(
        [sys.executable, "-m", "amuled_ma", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
        env={
            **os.environ,
            "GIT_PYTHON_REFRESH": "quiet",
            "PYTHONIOENCODING": "utf-8:backslashreplace",
        },
    )


def one_line(err: str) -> str:
    """The one ``amuled: error:`` line of stderr (and no traceback; progress lines aside)."""
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip() and not PLAIN_LINE.match(line)]
    assert len(lines) == 1 and lines[0].startswith("amuled: error: "), err
    return lines[0]
