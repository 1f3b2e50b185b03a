"""Means with confidence intervals (Student's t), no SciPy needed."""

from __future__ import annotations

import math
from collections.abc import Sequence
from statistics import NormalDist

# Two-sided 95% Student-t quantiles t_{0.975, df} for df = 1..30.
_T975 = (
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
    2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
)  # fmt: skip


def t_quantile(df: int, confidence: float = 0.95) -> float:
    """Two-sided Student-t critical value for ``df`` degrees of freedom.

    Exact (tabulated) for 95% and ``df <= 30``; otherwise the normal quantile with the
    Cornish-Fisher correction ``z + (z^3 + z) / (4 df)``, accurate to ~1e-3 beyond that.
    """
    if df < 1:
        return math.nan
    if abs(confidence - 0.95) < 1e-12 and df <= len(_T975):
        return _T975[df - 1]
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    return z + (z**3 + z) / (4 * df)


def mean_ci(values: Sequence[float], confidence: float = 0.95) -> dict[str, float]:
    """Mean, standard deviation and a ``confidence`` interval of the mean.

    Args:
        values: Per-episode values.
        confidence: Two-sided confidence level.

    Returns:
        ``{"mean", "std", "n", "ci_low", "ci_high", "half_width"}``; with one value the
        spread and the interval are undefined (NaN: one episode says nothing about the
        variability, so no "± 0" is claimed), with none every figure is NaN.

    """
    n = len(values)
    if n == 0:
        nan = math.nan
        return {"mean": nan, "std": nan, "n": 0, "ci_low": nan, "ci_high": nan, "half_width": nan}
    mean = sum(values) / n
    if n == 1:
        nan = math.nan
        return {"mean": mean, "std": nan, "n": 1, "ci_low": nan, "ci_high": nan, "half_width": nan}
    var = sum((v - mean) ** 2 for v in values) / (n - 1)
    std = math.sqrt(var)
    half = t_quantile(n - 1, confidence) * std / math.sqrt(n)
    return {
        "mean": mean,
        "std": std,
        "n": n,
        "ci_low": mean - half,
        "ci_high": mean + half,
        "half_width": half,
    }
