"""``amuled bench population --welch``: Welch's t and p, against R's printed example."""

import math

import pytest

from amuled_ma.bench.population import welch_t


def test_welch_t_is_rs_t_test_on_the_sleep_data():
    # R's example(t.test): t.test(extra ~ group, data = sleep) prints
    # "t = -1.8608, df = 17.776, p-value = 0.07939" for mean(group 1) - mean(group 2)
    group1 = [0.7, -1.6, -0.2, -1.2, -0.1, 3.4, 3.7, 0.8, 0.0, 2.0]
    group2 = [1.9, 0.8, 1.1, 0.1, -0.1, 4.4, 5.5, 1.6, 4.6, 3.4]
    t, p = welch_t(group2, group1)  # mean(b) - mean(a)
    assert t == pytest.approx(-1.8608, abs=1e-4) and p == pytest.approx(0.07939, abs=1e-5)


def test_welch_t_without_variance():
    assert welch_t([1.0, 1.0], [1.0, 1.0]) == (0.0, None)
    assert welch_t([1.0, 1.0], [2.0, 2.0]) == (math.inf, None)
