import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(autouse=True)
def private_data_folders(tmp_path, monkeypatch):
    """Keep every test away from the real user data folder and recordings."""
    monkeypatch.setenv("AMULED_DATA", str(tmp_path / "user-data"))
    monkeypatch.delenv("AMULED_RECORDINGS", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
