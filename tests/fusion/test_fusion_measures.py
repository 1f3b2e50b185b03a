"""BJS divergence and Deng entropy: hand values, the reference, and evidencelib."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from amuled_ma.fusion import bjs_divergence, deng_entropy, xiao_fusion
from amuled_ma.fusion import reference as ref

evidencelib = pytest.importorskip("evidencelib")

ATOMS = ("A", "B", "C")
FRAME = evidencelib.Frame.dst(ATOMS)
SUBSETS = [frozenset(c) for r in (1, 2, 3) for c in itertools.combinations(ATOMS, r)]


def test_bjs_hand_values():
    assert bjs_divergence([1.0, 0.0], [0.0, 1.0]) == pytest.approx(1.0)  # log base 2: max 1
    assert bjs_divergence([0.3, 0.7], [0.3, 0.7]) == 0.0
    # BJS([1, 0], [1/2, 1/2]) = 1/2 [log2(4/3)] + 1/2 [1/2 log2(2/3) + 1/2 log2(2)]
    expected = 0.5 * np.log2(4 / 3) + 0.25 * np.log2(2 / 3) + 0.25
    assert bjs_divergence([1.0, 0.0], [0.5, 0.5]) == pytest.approx(expected, abs=1e-15)


def test_bjs_matches_reference_and_is_symmetric_and_batched():
    rng = np.random.default_rng(5)
    a = rng.dirichlet(np.ones(4), size=50)
    b = rng.dirichlet(np.ones(4), size=50)
    a[:10, 0] = 0.0
    a[:10] /= a[:10].sum(axis=1, keepdims=True)
    got = bjs_divergence(a, b)
    assert got.shape == (50,)
    np.testing.assert_allclose(got, bjs_divergence(b, a), atol=1e-15)
    for i in range(50):
        ma = {frozenset([j]): v for j, v in enumerate(a[i])}
        mb = {frozenset([j]): v for j, v in enumerate(b[i])}
        assert got[i] == pytest.approx(ref.bjs(ma, mb), abs=1e-14)


@pytest.mark.parametrize("seed", range(20))
def test_deng_entropy_matches_evidencelib(seed):
    rng = np.random.default_rng(seed)
    focal = [SUBSETS[i] for i in rng.choice(len(SUBSETS), size=4, replace=False)]
    masses = rng.dirichlet(np.ones(4)) * 0.99 + 0.0025
    expected = evidencelib.MassFunction(FRAME, dict(zip(focal, masses, strict=True)))
    got = deng_entropy(masses, focal)
    assert got == pytest.approx(expected.deng_entropy(), abs=1e-12)
    assert got == pytest.approx(ref.deng_entropy(dict(zip(focal, masses, strict=True))), abs=1e-12)


def test_deng_entropy_of_singletons_is_shannon():
    p = np.array([[0.5, 0.25, 0.25, 0.0]])
    np.testing.assert_allclose(deng_entropy(p), [1.5])


def test_xiao_credibility_is_built_from_bjs():
    rng = np.random.default_rng(11)
    masses = rng.dirichlet(np.ones(3), size=4)
    result = xiao_fusion(masses, [{"a"}, {"b"}, {"c"}])
    distance = np.array(
        [[bjs_divergence(masses[i], masses[j]) for j in range(4)] for i in range(4)]
    )
    support = 1 / (distance.sum(axis=1) / 3)
    np.testing.assert_allclose(result.credibility, support / support.sum(), atol=1e-12)
    np.testing.assert_allclose(result.entropy, deng_entropy(masses), atol=1e-12)
