"""What makes two task states the same state for a moral panel.

A state is its observation *and* the prompt variables its state prompt is rendered from:
on FindMilk the number of crying babies still to pacify is in the prompt but not in the
observation, so two copies at one position with different counts are two states. The panel
(`MoralPanel`) and the fine-tuning feedback's
in-process memo (`Feedback`) key states with
`freeze` alike, as the belief store does with the rendered prompt.
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
