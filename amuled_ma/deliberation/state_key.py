"""What makes two task states the same state for a moral panel.

A state is its observation *and* its prompt variables: on FindMilk the number of crying
babies is in the prompt but not in the observation.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import numpy as np


def freeze(variables: Mapping[str, Any]) -> bytes:
    """Return a byte string identifying a dict of prompt variables (order-free)."""
    return b"\x1f" + json.dumps(
        variables, sort_keys=True, separators=(",", ":"), default=_json_default
    ).encode("utf-8")


def _json_default(value: object) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    return repr(value)
