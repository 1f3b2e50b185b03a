import math

import pytest

from amuled_ma.evaluate.stats import mean_ci, t_quantile


def test_mean_ci_hand_computed():
    # values 1..5: mean 3, sample std sqrt(2.5), t_{0.975,4} = 2.7764 (printed tables)
    out = mean_ci([1, 2, 3, 4, 5])
    assert out["mean"] == 3 and out["n"] == 5
    assert out["std"] == pytest.approx(math.sqrt(2.5))
    half = 2.7764 * math.sqrt(2.5) / math.sqrt(5)
    assert out["half_width"] == pytest.approx(half, abs=1e-4)
    assert (out["ci_low"], out["ci_high"]) == pytest.approx((3 - half, 3 + half), abs=1e-4)


def test_degenerate_cases():
    one = mean_ci([4.0])  # one value: no spread, no interval (not "± 0")
    assert one["mean"] == 4.0 and one["n"] == 1
    assert all(math.isnan(one[k]) for k in ("std", "ci_low", "ci_high", "half_width"))
    assert math.isnan(mean_ci([])["mean"])
    assert mean_ci([2.0] * 50)["half_width"] == 0.0
    assert math.isnan(t_quantile(0))


@pytest.mark.parametrize(
    ("df", "confidence", "printed"),
    [  # two-sided critical values of Student's t as printed in the tables (3 decimals)
        (1, 0.95, 12.706),
        (2, 0.95, 4.303),
        (4, 0.95, 2.776),
        (10, 0.95, 2.228),
        (30, 0.95, 2.042),
        (60, 0.95, 2.000),
        (120, 0.95, 1.980),
        (1e9, 0.95, 1.960),  # the normal quantile
        (10, 0.90, 1.812),
        (10, 0.99, 3.169),
        (100, 0.90, 1.660),
    ],
)
def test_t_quantile_is_the_printed_table(df, confidence, printed):
    assert t_quantile(df, confidence) == pytest.approx(printed, abs=5e-4)
