"""Defined behaviour for every degenerate input (docs/fusion.md, "Degenerate inputs")."""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.fusion import fuse, xiao_fusion
from amuled_ma.fusion.reference import fuse_beliefs

RULES = ["bjs-dst", "mean", "max", "vote", "single:0"]


@pytest.mark.parametrize("k", [2, 3, 5, 9])
def test_identical_beliefs_give_the_limit_m_power_k(k):
    m = np.array([0.5, 0.3, 0.2, 0.0])
    result = fuse(np.tile(m, (k, 1)), return_diagnostics=True)
    np.testing.assert_allclose(result.fused, m**k / (m**k).sum(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(result.credibility, 1 / k, atol=1e-15)
    np.testing.assert_allclose(result.weights, 1 / k, atol=1e-15)
    np.testing.assert_allclose(result.wae, m, atol=1e-15)
    assert np.all(np.isfinite(result.conflicts))
    np.testing.assert_allclose(fuse_beliefs(np.tile(m, (k, 1)).tolist()), result.fused, atol=1e-15)


def test_identical_beliefs_in_a_batch_do_not_disturb_other_states():
    regular = np.array([[0.7, 0.2, 0.1], [0.1, 0.2, 0.7]])
    same = np.tile([0.6, 0.3, 0.1], (2, 1))
    fused = fuse(np.stack([regular, same, regular]))
    np.testing.assert_allclose(fused[0], fuse(regular), atol=1e-15)
    np.testing.assert_allclose(fused[2], fuse(regular), atol=1e-15)
    np.testing.assert_allclose(fused[1], fuse(same), atol=1e-15)
    assert np.all(np.isfinite(fused))


def test_some_identical_sources_are_not_degenerate():
    beliefs = np.array([[0.6, 0.4], [0.6, 0.4], [0.2, 0.8]])
    result = fuse(beliefs, return_diagnostics=True)
    assert result.credibility[0] == result.credibility[1] > result.credibility[2]
    np.testing.assert_allclose(result.fused, fuse_beliefs(beliefs.tolist()), atol=1e-12)


@pytest.mark.parametrize("rule", RULES)
def test_single_cluster_returns_its_belief(rule):
    m = np.array([[0.1, 0.6, 0.3]])
    expected = [0.0, 1.0, 0.0] if rule == "vote" else m[0]
    result = fuse(m, rule, return_diagnostics=True)
    np.testing.assert_allclose(result.fused, expected, atol=1e-15)
    np.testing.assert_allclose(result.weights, [1.0])
    np.testing.assert_allclose(result.credibility, [1.0])
    assert result.conflicts.shape == (0,)


def test_single_cluster_general_focal_sets():
    result = xiao_fusion(np.array([[0.5, 0.5]]), [{"a"}, {"a", "b"}])
    np.testing.assert_allclose(result.fused, [0.5, 0.5])
    assert result.conflicts.shape == (0,)
    # Forcing the general combination on a singleton frame is also fine with k = 1.
    result = xiao_fusion(np.array([[0.5, 0.5]]), [{"a"}, {"b"}], closed_form=False)
    np.testing.assert_allclose(result.fused, [0.5, 0.5])


@pytest.mark.parametrize("rule", RULES)
def test_zeros_and_one_hot_beliefs_are_fine(rule):
    beliefs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]])
    out = fuse(beliefs, rule)
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    assert out.sum() == pytest.approx(1.0)


def test_action_nobody_believes_in_gets_zero():
    beliefs = np.array([[0.7, 0.3, 0.0], [0.2, 0.8, 0.0], [0.5, 0.5, 0.0]])
    assert fuse(beliefs)[2] == 0.0


def test_totally_conflicting_clusters_are_averaged_not_nan():
    # Classic Dempster on these raw beliefs would be K = 1 (undefined). Xiao's method
    # averages first (WAE = [1/2, 1/2, 0]) and WAE never conflicts totally with itself.
    result = fuse(np.eye(3)[:2], return_diagnostics=True)
    np.testing.assert_allclose(result.credibility, 0.5)
    np.testing.assert_allclose(result.fused, [0.5, 0.5, 0.0], atol=1e-15)
    np.testing.assert_allclose(result.conflicts, [0.5])
    result = fuse(np.eye(4), return_diagnostics=True)
    np.testing.assert_allclose(result.fused, 0.25, atol=1e-15)
    np.testing.assert_allclose(result.conflicts, 0.75, atol=1e-15)


def test_many_clusters_and_actions_do_not_underflow():
    # k = 300 clusters over 100 actions: max(WAE) is about 0.02 and 0.02^300 = 1e-510
    # underflows to 0 in float64; scaling by max(WAE) first keeps the result defined.
    beliefs = np.random.default_rng(3).dirichlet(np.ones(100), size=300)
    result = fuse(beliefs, return_diagnostics=True)
    assert result.wae.max() ** 300 == 0.0
    assert np.all(np.isfinite(result.fused)) and result.fused.sum() == pytest.approx(1.0)
    assert np.argmax(result.fused) == np.argmax(result.wae)
    assert np.all(np.isfinite(result.conflicts))


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (np.nan, "contains NaN or infinity"),
        (np.inf, "contains NaN or infinity"),
        (-0.1, "has a negative entry"),
        (0.9, "sums to"),
    ],
)
def test_invalid_rows_name_the_offending_index(bad, message):
    beliefs = np.full((4, 3, 2), 0.5)
    beliefs[2, 1, 0] = bad
    if bad == -0.1:
        beliefs[2, 1, 1] = 1.1
    for rule in RULES:
        with pytest.raises(
            ValueError, match=rf"beliefs\[2, 1\] is not a probability vector: {message}"
        ):
            fuse(beliefs, rule)
    with pytest.raises(ValueError, match=rf"masses\[2, 1\] .*{message}"):
        xiao_fusion(beliefs, [{"a"}, {"b"}])


def test_sum_tolerance_and_rescaling():
    # Off by less than 1e-6: accepted and rescaled to sum to 1.
    beliefs = np.array([[0.5, 0.5 + 5e-7], [0.2, 0.8]])
    out = fuse(beliefs, "single:0")
    assert out.sum() == pytest.approx(1.0, abs=1e-15)
    with pytest.raises(ValueError, match=r"beliefs\[0\] .*sums to"):
        fuse(np.array([[0.5, 0.5 + 2e-6], [0.2, 0.8]]))


@pytest.mark.parametrize("shape", [(3,), (0, 3), (3, 0)], ids=["1-d", "no clusters", "no actions"])
def test_bad_shapes(shape):
    with pytest.raises(ValueError):
        fuse(np.ones(shape) / max(shape[-1], 1))


def test_empty_batch_and_non_numeric_input():
    assert fuse(np.zeros((0, 5, 4))).shape == (0, 4)
    assert fuse(np.zeros((0, 5, 4)), return_diagnostics=True).conflicts.shape == (0, 4)
    with pytest.raises(ValueError, match="array of numbers"):
        fuse([["a", "b"]])


def test_invalid_focal_sets():
    m = np.array([[0.5, 0.5]])
    with pytest.raises(ValueError, match="empty set"):
        xiao_fusion(m, [{"a"}, set()])
    with pytest.raises(ValueError, match="listed twice"):
        xiao_fusion(m, [{"a"}, {"a"}])
    with pytest.raises(ValueError, match="set of hypotheses"):
        xiao_fusion(m, ["ab", {"a"}])
    with pytest.raises(ValueError, match="focal sets were given"):
        xiao_fusion(m, [{"a"}, {"b"}, {"c"}])
    with pytest.raises(ValueError, match="closed_form=True"):
        xiao_fusion(m, [{"a"}, {"a", "b"}], closed_form=True)


@pytest.mark.parametrize("rule", RULES)
def test_input_is_not_modified_and_output_is_float64(rule):
    beliefs = np.array([[0.5, 0.25, 0.25], [0.2, 0.3, 0.5]], dtype=np.float32)
    before = beliefs.copy()
    out = fuse(beliefs, rule)
    np.testing.assert_array_equal(beliefs, before)
    assert out.dtype == np.float64
    lists = fuse(beliefs.tolist(), rule)  # nested lists work too
    np.testing.assert_allclose(lists, out)
