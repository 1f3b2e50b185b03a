"""Fixtures of the task tests: one torch thread (small tensors are faster that way)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_thread():
    torch.set_num_threads(1)
