"""Shared test fixtures.

Tests that read the authors' recordings use the ``recordings_dir`` fixture: it points at
``../shared/amuled-recordings`` beside the checkout (or ``$AMULED_RECORDINGS``) and skips
the test with a reason when that folder is absent, so a lone clone still passes.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# No test reaches the network: a paper authors' recording found nowhere is not fetched
# (amuled_ma.authors.download). The fetch's own tests unset this and serve on 127.0.0.1.
os.environ["AMULED_OFFLINE"] = "1"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Put the tests marked ``slow`` first, keeping the order within each group.

    Handed out first (``--maxschedchunk`` in ``.ci/test``), the long tests spread over the
    workers from the start instead of leaving one worker on a long test at the end.
    """
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


def _recordings_path() -> Path:
    env = os.environ.get("AMULED_RECORDINGS")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "amuled-recordings"


@pytest.fixture(scope="session")
def recordings_dir() -> Path:
    """The folder of real LLM recordings; skips when it is not beside the checkout."""
    path = _recordings_path()
    if not path.is_dir():
        pytest.skip(
            f"recordings not found at {path} "
            "(set AMULED_RECORDINGS or put shared/ beside the clone)"
        )
    return path


@pytest.fixture(scope="session")
def load_recording(recordings_dir: Path):
    """Return a loader ``name -> parsed JSON`` for one recording file (cached)."""
    cache: dict[str, dict] = {}

    def load(name: str) -> dict:
        if name not in cache:
            cache[name] = json.loads((recordings_dir / name).read_text())
        return cache[name]

    return load
