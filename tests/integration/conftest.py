"""Fixtures of the real-server integration tests (``tests/ollama_server_fixture.py``).

Every test here needs a real Ollama server; the ``ollama_host`` fixture brings one up
once per session (skips with a reason without a binary, fails under ``CI=true``).
"""

from pathlib import Path

import pytest
from ollama_server_fixture import *  # noqa: F403

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test of this directory ``ollama``."""
    for item in items:
        if HERE in Path(item.path).resolve().parents:
            item.add_marker(pytest.mark.ollama)
