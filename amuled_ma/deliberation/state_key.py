"""What makes two task states the same state for a moral panel.

A state is its observation *and* its prompt variables: on FindMilk the number of crying
babies is in the prompt but not in the observation.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any


def freeze(variables: Mapping[str, Any]) -> bytes:
    """Return a byte string identifying a dict of prompt variables (order-free)."""
    return b"\x1f" + json.dumps(
        variables, sort_keys=True, separators=(",", ":"), default=_json_default
    ).encode("utf-8")


def _json_default(value: object) -> Any:
    return value.tolist() if hasattr(value, "tolist") else repr(value)  # numpy: Python values
