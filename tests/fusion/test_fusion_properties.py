"""Property tests (hypothesis) of fuse and of the pure-Python reference."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from amuled_ma.fusion import fuse, xiao_fusion
from amuled_ma.fusion.reference import fuse_beliefs

SYMMETRIC_RULES = ["bjs-dst", "mean", "max", "vote"]


@st.composite
def belief_matrices(draw, max_clusters=6, max_actions=5, batch=False):
    k = draw(st.integers(1, max_clusters))
    n = draw(st.integers(1, max_actions))
    shape = ((draw(st.integers(1, 3)),) if batch else ()) + (k, n)
    raw = draw(
        arrays(
            np.float64,
            shape,
            elements=st.one_of(st.just(0.0), st.floats(1e-6, 1.0), st.sampled_from([0.1, 0.5])),
        )
    )
    raw[..., 0] += (raw.sum(axis=-1) == 0).astype(float)  # no all-zero row
    return raw / raw.sum(axis=-1, keepdims=True)


def _is_probability_vector(x):
    return np.all(np.isfinite(x)) and np.all(x >= 0) and np.allclose(x.sum(axis=-1), 1.0)


@settings(max_examples=60, deadline=None)
@given(belief_matrices(batch=True), st.sampled_from([*SYMMETRIC_RULES, "single:0"]))
def test_output_is_a_probability_vector(beliefs, rule):
    out = fuse(beliefs, rule)
    assert out.shape == beliefs.shape[:-2] + beliefs.shape[-1:]
    assert _is_probability_vector(out)


@settings(max_examples=60, deadline=None)
@given(belief_matrices(), st.sampled_from(SYMMETRIC_RULES), st.randoms())
def test_invariant_to_permuting_clusters(beliefs, rule, rnd):
    order = list(range(beliefs.shape[0]))
    rnd.shuffle(order)
    np.testing.assert_allclose(fuse(beliefs[order], rule), fuse(beliefs, rule), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(belief_matrices(batch=True), st.data())
def test_single_returns_cluster_i(beliefs, data):
    i = data.draw(st.integers(0, beliefs.shape[-2] - 1))
    np.testing.assert_array_equal(fuse(beliefs, f"single:{i}"), beliefs[..., i, :])


@settings(max_examples=60, deadline=None)
@given(belief_matrices(max_clusters=1, batch=True), st.integers(1, 7))
def test_mean_of_equal_beliefs_returns_them(one, k):
    beliefs = np.repeat(one, k, axis=-2)
    np.testing.assert_allclose(fuse(beliefs, "mean"), one[..., 0, :], atol=1e-15)


@settings(max_examples=60, deadline=None)
@given(belief_matrices(batch=True))
def test_batched_equals_one_by_one_and_reference(beliefs):
    batched = fuse(beliefs)
    for b in range(beliefs.shape[0]):
        np.testing.assert_allclose(batched[b], fuse(beliefs[b]), atol=1e-12)
        np.testing.assert_allclose(batched[b], fuse_beliefs(beliefs[b].tolist()), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(belief_matrices(batch=True))
def test_closed_form_equals_general_dempster_combination(beliefs):
    sets = [{a} for a in range(beliefs.shape[-1])]
    closed = xiao_fusion(beliefs, sets)
    general = xiao_fusion(beliefs, sets, closed_form=False)
    np.testing.assert_allclose(closed.fused, general.fused, atol=1e-12)
    np.testing.assert_allclose(closed.conflicts, general.conflicts, atol=1e-12)
    np.testing.assert_allclose(closed.fused, fuse(beliefs), atol=1e-15)


@settings(max_examples=40, deadline=None)
@given(belief_matrices())
def test_diagnostics_are_well_formed(beliefs):
    result = fuse(beliefs, return_diagnostics=True)
    k = beliefs.shape[0]
    for field in (result.weights, result.credibility):
        assert field.shape == (k,) and np.all(field >= 0)
        np.testing.assert_allclose(field.sum(), 1.0)
    assert np.all(result.entropy >= -1e-12)
    assert result.conflicts.shape == (k - 1,)
    assert np.all((result.conflicts >= 0) & (result.conflicts <= 1))
