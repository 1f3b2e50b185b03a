"""The rule registry and the baseline rules: mean, max, vote (with its tie rule), single."""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.fusion import RULES, FusionResult, fuse, register_rule, unregister_rule

BELIEFS = np.array(
    [
        [0.70, 0.10, 0.10, 0.10],
        [0.60, 0.20, 0.10, 0.10],
        [0.10, 0.10, 0.10, 0.70],
    ]
)


def test_builtin_rules_are_registered():
    assert {"bjs-dst", "mean", "max", "vote", "single"} <= set(RULES)
    assert RULES["single"].takes_param
    assert RULES["mean"].takes_weights and RULES["vote"].takes_weights
    assert not RULES["bjs-dst"].takes_weights
    assert RULES["bjs-dst"].summary.startswith("Xiao")


def test_mean_is_the_average_and_takes_weights():
    np.testing.assert_allclose(fuse(BELIEFS, "mean"), BELIEFS.mean(axis=0), atol=1e-15)
    w = np.array([1.0, 3.0, 0.0])
    np.testing.assert_allclose(
        fuse(BELIEFS, "mean", weights=w), (0.25 * BELIEFS[0] + 0.75 * BELIEFS[1]), atol=1e-15
    )
    # Per-state weights broadcast over a batch.
    batch = np.stack([BELIEFS, BELIEFS[::-1]])
    weights = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    np.testing.assert_allclose(fuse(batch, "mean", weights=weights), [BELIEFS[0], BELIEFS[2]])


def test_max_is_renormalised_per_action_maximum():
    top = np.array([0.70, 0.20, 0.10, 0.70])
    np.testing.assert_allclose(fuse(BELIEFS, "max"), top / top.sum(), atol=1e-15)


def test_vote_majority():
    assert fuse(BELIEFS, "vote").tolist() == [1.0, 0.0, 0.0, 0.0]


def test_vote_tie_between_actions_splits_mass_equally():
    beliefs = np.array([[0.7, 0.3, 0, 0], [0.2, 0.8, 0, 0], [0, 0, 0.1, 0.9], [0, 0, 0.9, 0.1]])
    assert fuse(beliefs, "vote").tolist() == [0.25, 0.25, 0.25, 0.25]
    assert fuse(beliefs[:2], "vote").tolist() == [0.5, 0.5, 0.0, 0.0]


def test_vote_tie_inside_a_cluster_splits_its_vote():
    # Cluster 0 is torn between actions 0 and 1: half a vote each; cluster 1 votes 1.
    beliefs = np.array([[0.4, 0.4, 0.2, 0.0], [0.1, 0.6, 0.2, 0.1]])
    assert fuse(beliefs, "vote").tolist() == [0.0, 1.0, 0.0, 0.0]
    # A uniform belief gives a quarter vote to every action.
    beliefs = np.array([[0.25] * 4, [0.1, 0.6, 0.2, 0.1], [0.6, 0.1, 0.2, 0.1]])
    assert fuse(beliefs, "vote").tolist() == [0.5, 0.5, 0.0, 0.0]


def test_vote_tie_is_independent_of_action_order():
    beliefs = np.array([[0.6, 0.4, 0, 0], [0.4, 0.6, 0, 0]])
    assert fuse(beliefs, "vote").tolist() == [0.5, 0.5, 0.0, 0.0]
    assert fuse(beliefs[:, ::-1], "vote").tolist() == [0.0, 0.0, 0.5, 0.5]


def test_vote_weights_scale_votes_and_tolerate_rounding():
    beliefs = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 1.0, 0]])
    assert fuse(beliefs, "vote", weights=[3, 1, 1]).tolist() == [1.0, 0.0, 0.0]
    # 0.1 + 0.2 != 0.3 in floating point, but it is still a tie.
    assert fuse(beliefs, "vote", weights=[0.3, 0.1, 0.2]).tolist() == [0.5, 0.5, 0.0]


def test_single_returns_one_cluster_and_accepts_negative_index():
    np.testing.assert_array_equal(fuse(BELIEFS, "single:1"), BELIEFS[1])
    np.testing.assert_array_equal(fuse(BELIEFS, "single:-1"), BELIEFS[2])
    for bad in ("single:3", "single:x", "single", "single:"):
        with pytest.raises(ValueError, match="single"):
            fuse(BELIEFS, bad)


def test_unknown_rule_and_misused_options_are_errors():
    with pytest.raises(ValueError, match=r"unknown fusion rule 'median'.*bjs-dst"):
        fuse(BELIEFS, "median")
    with pytest.raises(ValueError, match="takes no weights"):
        fuse(BELIEFS, "bjs-dst", weights=[1, 1, 1])
    with pytest.raises(ValueError, match="takes no parameter"):
        fuse(BELIEFS, "mean:2")
    with pytest.raises(ValueError, match=r"weights\[1\]"):
        fuse(BELIEFS, "mean", weights=[1, -1, 1])
    with pytest.raises(ValueError, match="all zero"):
        fuse(BELIEFS, "mean", weights=[0, 0, 0])
    with pytest.raises(ValueError, match="do not broadcast"):
        fuse(BELIEFS, "mean", weights=[1, 1])


def test_register_rule_decorator_and_unregister():
    @register_rule("test-geometric")
    def geometric(beliefs, *, weights, param, diagnostics):
        """Geometric mean, renormalised."""
        g = np.exp(np.log(beliefs + 1e-300).mean(axis=-2))
        return g / g.sum(axis=-1, keepdims=True)

    try:
        assert RULES["test-geometric"].summary == "Geometric mean, renormalised."
        out = fuse(np.stack([BELIEFS, BELIEFS]), "test-geometric")
        assert out.shape == (2, 4)
        np.testing.assert_allclose(out.sum(axis=-1), 1.0)
        # A rule returning a plain array still gets generic diagnostics.
        result = fuse(BELIEFS, "test-geometric", return_diagnostics=True)
        assert isinstance(result, FusionResult)
        np.testing.assert_allclose(result.weights, 1 / 3)
        assert result.conflicts.shape == (0,)
        with pytest.raises(ValueError, match="already registered"):
            register_rule("test-geometric")(geometric)
        register_rule("test-geometric", replace=True)(geometric)
    finally:
        unregister_rule("test-geometric")
    assert "test-geometric" not in RULES
    with pytest.raises(ValueError, match="name"):
        register_rule("bad:name")


def test_rule_returning_wrong_shape_is_reported():
    @register_rule("test-broken")
    def broken(beliefs, **_):
        return beliefs

    try:
        with pytest.raises(ValueError, match="returned shape"):
            fuse(BELIEFS, "test-broken")
    finally:
        unregister_rule("test-broken")


@pytest.mark.parametrize("rule", ["bjs-dst", "mean", "max", "vote", "single:0"])
def test_diagnostics_for_every_rule(rule):
    batch = np.stack([BELIEFS, BELIEFS[[2, 0, 1]]])
    result = fuse(batch, rule, return_diagnostics=True)
    np.testing.assert_array_equal(result.fused, fuse(batch, rule))
    assert result.weights.shape == result.credibility.shape == result.entropy.shape == (2, 3)
    np.testing.assert_allclose(result.weights.sum(axis=-1), 1.0)
    np.testing.assert_allclose(result.credibility.sum(axis=-1), 1.0)
    assert result.conflicts.shape == ((2, 2) if rule == "bjs-dst" else (2, 0))
    assert result.rule == rule


def test_rule_specific_weights_explain_the_decision():
    vote = fuse(BELIEFS, "vote", return_diagnostics=True)
    np.testing.assert_allclose(vote.weights, [0.5, 0.5, 0.0])  # the two voters for action 0
    single = fuse(BELIEFS, "single:2", return_diagnostics=True)
    np.testing.assert_array_equal(single.weights, [0.0, 0.0, 1.0])
    mx = fuse(BELIEFS, "max", return_diagnostics=True)
    top = np.array([0.70, 0.20, 0.10, 0.70]) / 1.7
    # cluster 0 holds the max of action 0 and shares action 2 with the others.
    np.testing.assert_allclose(
        mx.weights, [top[0] + top[2] / 3, top[1] + top[2] / 3, top[3] + top[2] / 3]
    )
