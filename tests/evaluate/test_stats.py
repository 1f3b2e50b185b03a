import math

import pytest

from amuled_ma.evaluate.stats import mean_ci, t_quantile


def test_mean_ci_hand_computed():
    # values 1..5: mean 3, sample std sqrt(2.5), t_{0.975,4} = 2.776
    out = mean_ci([1, 2, 3, 4, 5])
    assert out["mean"] == 3 and out["n"] == 5
    assert out["std"] == pytest.approx(math.sqrt(2.5))
    half = 2.776 * math.sqrt(2.5) / math.sqrt(5)
    assert out["ci_low"] == pytest.approx(3 - half) and out["ci_high"] == pytest.approx(3 + half)


def test_degenerate_cases():
    one = mean_ci([4.0])  # one value: no spread, no interval (not "± 0")
    assert one["mean"] == 4.0 and one["n"] == 1
    assert all(math.isnan(one[k]) for k in ("std", "ci_low", "ci_high", "half_width"))
    assert math.isnan(mean_ci([])["mean"])
    assert mean_ci([2.0] * 50)["half_width"] == 0.0


def test_t_quantile_large_df_and_other_levels():
    assert t_quantile(49) == pytest.approx(2.0096, abs=2e-3)
    assert t_quantile(1000) == pytest.approx(1.962, abs=2e-3)
    assert t_quantile(100, 0.90) == pytest.approx(1.660, abs=3e-3)
