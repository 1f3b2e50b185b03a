"""Fusion (numpy): beliefs ``(..., k, n)`` in, one ``(..., n)`` out (docs/fusion.md)."""

from __future__ import annotations

from amuled_ma.fusion import moral_uncertainty  # noqa: F401  (registers mec, nash-vote, ...)
from amuled_ma.fusion.rules import RULES, RuleSpec, fuse, register_rule, unregister_rule
from amuled_ma.fusion.xiao import (
    SUM_TOLERANCE,
    FusionResult,
    bjs_divergence,
    dempster_combine,
    deng_entropy,
    xiao_fusion,
)

__all__ = [
    "RULES",
    "SUM_TOLERANCE",
    "FusionResult",
    "RuleSpec",
    "bjs_divergence",
    "dempster_combine",
    "deng_entropy",
    "fuse",
    "register_rule",
    "unregister_rule",
    "xiao_fusion",
]
