"""A per-state pure-Python Xiao (2019) fusion (test oracle, benchmark baseline), no shared code.

Mass functions are dicts of frozensets; the input is not validated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

Mass = Mapping[frozenset, float]


def _xlog2x(x: float) -> float:
    return x * math.log2(x) if x > 0 else 0.0


def bjs(m1: Mass, m2: Mass) -> float:
    """Belief Jensen-Shannon divergence of two mass functions (log base 2)."""
    total = 0.0
    for focal in set(m1) | set(m2):
        a = m1.get(focal, 0.0)
        b = m2.get(focal, 0.0)
        if a > 0:
            total += 0.5 * a * math.log2(2 * a / (a + b))
        if b > 0:
            total += 0.5 * b * math.log2(2 * b / (a + b))
    return max(total, 0.0)


def deng_entropy(m: Mass) -> float:
    """Deng entropy ``-sum_A m(A) log2(m(A) / (2^|A| - 1))``."""
    return -sum(_xlog2x(v) - v * math.log2(2 ** len(a) - 1) for a, v in m.items())


def dempster(m1: Mass, m2: Mass) -> tuple[dict[frozenset, float], float]:
    """Dempster's rule of combination; returns ``(combined, K)``; ``ValueError`` at ``K = 1``."""
    joint: dict[frozenset, float] = {}
    conflict = 0.0
    for a, x in m1.items():
        for b, y in m2.items():
            c = a & b
            if c:
                joint[c] = joint.get(c, 0.0) + x * y
            else:
                conflict += x * y
    norm = sum(joint.values())
    if norm <= 0:
        raise ValueError("total conflict (K = 1): Dempster's rule is undefined")
    return {c: v / norm for c, v in joint.items()}, conflict


def xiao_fuse(masses: Sequence[Mass]) -> tuple[dict[frozenset, float], dict[str, Any]]:
    """Fuse ``k`` mass functions: ``(fused, diagnostics)`` (lists of `FusionResult`'s fields)."""
    k = len(masses)
    # Step 1: credibility from the average BJS distance to the other sources.
    if k == 1:
        credibility = [1.0]
    else:
        distance = [
            sum(bjs(masses[i], masses[j]) for j in range(k) if j != i) / (k - 1) for i in range(k)
        ]
        if any(d == 0 for d in distance):  # limit: share among the zero-distance sources
            zeros = [1.0 if d == 0 else 0.0 for d in distance]
            credibility = [z / sum(zeros) for z in zeros]
        else:
            support = [1 / d for d in distance]
            credibility = [s / sum(support) for s in support]
    # Step 2: information volume from Deng entropy.
    entropy = [deng_entropy(m) for m in masses]
    volume = [math.exp(e) for e in entropy]
    volume = [v / sum(volume) for v in volume]
    # Step 3: adjusted credibility, weighted average evidence, k - 1 combinations.
    adjusted = [c * v for c, v in zip(credibility, volume, strict=True)]
    weights = [a / sum(adjusted) for a in adjusted]
    wae: dict[frozenset, float] = {}
    for w, m in zip(weights, masses, strict=True):
        for focal, value in m.items():
            wae[focal] = wae.get(focal, 0.0) + w * value
    fused = dict(wae)
    conflicts = []
    for _ in range(k - 1):
        fused, conflict = dempster(fused, wae)
        conflicts.append(conflict)
    diagnostics = {
        "weights": weights,
        "credibility": credibility,
        "entropy": entropy,
        "conflicts": conflicts,
        "wae": wae,
    }
    return fused, diagnostics


def fuse_beliefs(beliefs: Sequence[Sequence[float]]) -> list[float]:
    """Fuse ``k`` belief vectors over actions (singleton focal elements) with Xiao (2019)."""
    masses = [{frozenset([a]): p for a, p in enumerate(row)} for row in beliefs]
    fused, _ = xiao_fuse(masses)
    return [fused.get(frozenset([a]), 0.0) for a in range(len(beliefs[0]))]
