"""Means with Student-t confidence intervals (``scipy.stats``)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats


def t_quantile(df: float, confidence: float = 0.95) -> float:
    """Two-sided Student-t critical value ``t_{(1 + confidence) / 2, df}`` (NaN for df < 1)."""
    return math.nan if df < 1 else float(stats.t.ppf(0.5 + confidence / 2, df))


def mean_ci(values: Sequence[float], confidence: float = 0.95) -> dict[str, float]:
    """Mean, std and ``confidence`` interval: ``mean, std, n, ci_low, ci_high, half_width``.

    With one value the spread and interval are NaN (no "± 0" is claimed); with none, all is NaN.
    """
    n = len(values)
    array = np.asarray(values, dtype=float)
    mean = float(array.mean()) if n else math.nan
    std = float(array.std(ddof=1)) if n > 1 else math.nan
    half = t_quantile(n - 1, confidence) * std / math.sqrt(n) if n > 1 else math.nan  # t · s / √n
    return {
        "mean": mean,
        "std": std,
        "n": n,
        "ci_low": mean - half,
        "ci_high": mean + half,
        "half_width": half,
    }
