"""The fusion arbiter: many moral clusters' beliefs in, one belief over the actions out.

## Description

Each moral-cluster agent gives a belief vector over the task's actions; the arbiter fuses
the ``k`` vectors of a state into one basic probability assignment, which becomes the
shaping reward. Pure numpy (no torch, no LLM); every function is batched over leading
dimensions, so one call fuses the beliefs of thousands of parallel environments.

```python
import numpy as np
from amuled_ma.fusion import fuse, xiao_fusion

fused = fuse(beliefs)                      # (..., k, n) -> (..., n), rule "bjs-dst"
result = fuse(beliefs, return_diagnostics=True)
result.weights, result.credibility, result.entropy, result.conflicts
fuse(beliefs, "mean"); fuse(beliefs, "max"); fuse(beliefs, "vote"); fuse(beliefs, "single:0")
fuse(beliefs, "mec"); fuse(beliefs, "nash-vote"); fuse(beliefs, "variance-vote")
fuse(beliefs, "borda")
xiao_fusion(masses, [{"A"}, {"B"}, {"C"}, {"A", "C"}])   # general focal elements
```

## Contents

- :func:`fuse` and the rule registry (:func:`register_rule`, :data:`RULES`):
  :mod:`amuled_ma.fusion.rules` (the rules and the ``vote`` tie rule are documented there).
- :func:`xiao_fusion`, :func:`dempster_combine`, :func:`bjs_divergence`,
  :func:`deng_entropy`, :class:`FusionResult`: :mod:`amuled_ma.fusion.xiao` (the maths
  and every degenerate case are documented there).
- ``mec``, ``nash-vote``, ``variance-vote``, ``borda``, the rules for acting under moral
  uncertainty: :mod:`amuled_ma.fusion.moral_uncertainty` (their mapping from beliefs and
  their sources are documented there).
- :mod:`amuled_ma.fusion.reference`: a plain per-state pure-Python implementation with
  dicts of frozensets, used as a test oracle and as the benchmark's baseline.
"""

from __future__ import annotations

from amuled_ma.fusion import moral_uncertainty  # noqa: F401  (registers mec, nash-vote, ...)
from amuled_ma.fusion._validate import SUM_TOLERANCE
from amuled_ma.fusion.rules import RULES, RuleSpec, fuse, register_rule, unregister_rule
from amuled_ma.fusion.xiao import (
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
