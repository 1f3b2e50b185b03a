"""Xiao (2019), Information Fusion 46:23-32: the paper's five-sensor example, to 1e-9."""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.fusion import xiao_fusion
from amuled_ma.fusion.reference import xiao_fuse

FOCAL = [{"A"}, {"B"}, {"C"}, {"A", "C"}]
MASSES = np.array(
    [
        [0.41, 0.29, 0.30, 0.00],
        [0.00, 0.90, 0.10, 0.00],
        [0.58, 0.07, 0.00, 0.35],
        [0.55, 0.10, 0.00, 0.35],
        [0.60, 0.10, 0.00, 0.30],
    ]
)
EXPECTED_WAE = [0.5315501409, 0.1471577064, 0.0520764007, 0.2692157521]
EXPECTED_FUSED = [0.9894584021, 0.0002082831, 0.0060651478, 0.0042681670]


def test_weighted_average_evidence_matches_paper():
    result = xiao_fusion(MASSES, FOCAL)
    np.testing.assert_allclose(result.wae, EXPECTED_WAE, rtol=0, atol=1e-9)


def test_fused_masses_match_paper():
    result = xiao_fusion(MASSES, FOCAL)
    assert result.focal_sets == tuple(frozenset(s) for s in FOCAL)
    np.testing.assert_allclose(result.fused, EXPECTED_FUSED, rtol=0, atol=1e-9)


def test_diagnostics_are_consistent():
    result = xiao_fusion(MASSES, FOCAL)
    for field in (result.weights, result.credibility):
        assert field.shape == (5,)
        assert np.all(field > 0)
        assert field.sum() == pytest.approx(1.0, abs=1e-12)
    # m2 = [0, 0.9, 0.1, 0] contradicts the others: least credible and least weight.
    assert np.argmin(result.credibility) == 1
    assert np.argmin(result.weights) == 1
    # Deng entropy of m1 (singletons only) is its Shannon entropy.
    p = MASSES[0, :3]
    assert result.entropy[0] == pytest.approx(-(p * np.log2(p)).sum(), abs=1e-12)
    assert result.conflicts.shape == (4,)
    assert np.all((result.conflicts > 0) & (result.conflicts < 1))
    # First combination: K = sum of WAE(X) WAE(Y) over ordered disjoint pairs (X, Y):
    # {A}-{B}, {A}-{C}, {B}-{C}, {B}-{A,C}.
    w = np.array(EXPECTED_WAE)
    k1 = 2 * (w[0] * w[1] + w[1] * w[2] + w[1] * w[3] + w[0] * w[2])
    assert result.conflicts[0] == pytest.approx(k1, abs=1e-9)


def test_general_and_singleton_frames_agree_on_a_batch():
    batch = np.stack([MASSES, MASSES[::-1], MASSES[[1, 0, 2, 3, 4]]])
    result = xiao_fusion(batch, FOCAL)
    assert result.fused.shape == (3, 4)
    for b in range(3):
        np.testing.assert_allclose(result.fused[b], EXPECTED_FUSED, atol=1e-9)


def test_pure_python_reference_matches_paper():
    masses = [
        {frozenset(s): float(v) for s, v in zip(FOCAL, row, strict=True) if v > 0} for row in MASSES
    ]
    fused, diag = xiao_fuse(masses)
    got = [fused.get(frozenset(s), 0.0) for s in FOCAL]
    np.testing.assert_allclose(got, EXPECTED_FUSED, atol=1e-9)
    wae = [diag["wae"].get(frozenset(s), 0.0) for s in FOCAL]
    np.testing.assert_allclose(wae, EXPECTED_WAE, atol=1e-9)
