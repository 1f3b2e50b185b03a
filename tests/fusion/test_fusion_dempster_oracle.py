"""Dempster's rule checked against an independent library (evidencelib, PyPI) as an oracle."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from amuled_ma.fusion import dempster_combine, xiao_fusion
from amuled_ma.fusion.reference import dempster, xiao_fuse

evidencelib = pytest.importorskip("evidencelib")
from evidencelib.exceptions import TotalConflictError  # noqa: E402

ATOMS = ("A", "B", "C", "D")
FRAME = evidencelib.Frame.dst(ATOMS)
SUBSETS = [frozenset(c) for r in range(1, len(ATOMS) + 1) for c in itertools.combinations(ATOMS, r)]


def _random_mass(rng: np.random.Generator) -> dict[frozenset, float]:
    n = int(rng.integers(1, 6))
    focal = rng.choice(len(SUBSETS), size=n, replace=False)
    values = rng.dirichlet(np.ones(n)) * 0.98 + 0.02 / n  # no mass below evidencelib's 1e-9
    return {SUBSETS[f]: float(v) for f, v in zip(focal, values, strict=True)}


def _oracle(m1, m2):
    a = evidencelib.MassFunction(FRAME, m1)
    b = evidencelib.MassFunction(FRAME, m2)
    return a.dempster(b)


@pytest.mark.parametrize("seed", range(200))
def test_vectorized_and_reference_dempster_match_evidencelib(seed):
    rng = np.random.default_rng(seed)
    m1, m2 = _random_mass(rng), _random_mass(rng)
    try:
        expected = _oracle(m1, m2)
    except TotalConflictError:
        with pytest.raises(ValueError, match="total conflict"):
            dempster(m1, m2)
        with pytest.raises(ValueError, match="total conflict"):
            dempster_combine(
                np.array(list(m1.values())), list(m1), np.array(list(m2.values())), list(m2)
            )
        return
    masses, sets, conflict = dempster_combine(
        np.array(list(m1.values())), list(m1), np.array(list(m2.values())), list(m2)
    )
    reference, ref_conflict = dempster(m1, m2)
    for subset in SUBSETS:
        want = expected.mass(subset)
        got = masses[sets.index(subset)] if subset in sets else 0.0
        assert got == pytest.approx(want, abs=1e-12)
        assert reference.get(subset, 0.0) == pytest.approx(want, abs=1e-12)
    # evidencelib's unnormalised conjunctive rule puts the conflict K on the empty set.
    unnormalised = evidencelib.MassFunction(FRAME, m1).conjunctive(
        evidencelib.MassFunction(FRAME, m2)
    )
    assert float(conflict) == pytest.approx(unnormalised.conflict, abs=1e-12)
    assert ref_conflict == pytest.approx(unnormalised.conflict, abs=1e-12)


def test_batched_dempster_matches_evidencelib_row_by_row():
    rng = np.random.default_rng(7)
    sets1 = [SUBSETS[i] for i in (0, 4, 10, 14)]
    sets2 = [SUBSETS[i] for i in (1, 5, 14)]
    a = rng.dirichlet(np.ones(len(sets1)), size=(6, 3))
    b = rng.dirichlet(np.ones(len(sets2)), size=(3,))  # broadcasts against (6, 3)
    masses, sets, conflict = dempster_combine(a, sets1, b, sets2)
    assert masses.shape[:-1] == conflict.shape == (6, 3)
    for i, j in itertools.product(range(6), range(3)):
        expected = _oracle(
            dict(zip(sets1, a[i, j], strict=True)), dict(zip(sets2, b[j], strict=True))
        )
        for col, subset in enumerate(sets):
            assert masses[i, j, col] == pytest.approx(expected.mass(subset), abs=1e-12)


def test_total_conflict_raises_with_batch_index():
    a = np.array([[1.0, 0.0], [0.0, 1.0]])
    b = np.array([[0.0, 1.0], [0.0, 1.0]])
    with pytest.raises(ValueError, match=r"total conflict \(K = 1\) at batch index \(0,\)"):
        dempster_combine(a, [{"x"}, {"y"}], b, [{"x"}, {"y"}])
    with pytest.raises(TotalConflictError):
        _oracle({frozenset("A"): 1.0}, {frozenset("B"): 1.0})


@pytest.mark.parametrize("seed", range(40))
def test_general_xiao_fusion_matches_reference_on_random_focal_sets(seed):
    rng = np.random.default_rng(1000 + seed)
    n_focal = int(rng.integers(2, 7))
    focal = [SUBSETS[i] for i in rng.choice(len(SUBSETS), size=n_focal, replace=False)]
    k = int(rng.integers(1, 6))
    masses = rng.dirichlet(np.ones(n_focal), size=k)
    masses[rng.random(masses.shape) < 0.2] = 0.0
    masses[masses.sum(axis=1) == 0, 0] = 1.0
    masses /= masses.sum(axis=1, keepdims=True)
    result = xiao_fusion(masses, focal)
    fused, diag = xiao_fuse([dict(zip(focal, row, strict=True)) for row in masses])
    assert set(fused) <= set(result.focal_sets)
    for col, subset in enumerate(result.focal_sets):
        assert result.fused[col] == pytest.approx(fused.get(subset, 0.0), abs=1e-9)
    np.testing.assert_allclose(result.weights, diag["weights"], atol=1e-9)
    np.testing.assert_allclose(result.credibility, diag["credibility"], atol=1e-9)
    np.testing.assert_allclose(result.entropy, diag["entropy"], atol=1e-9)
    np.testing.assert_allclose(result.conflicts, diag["conflicts"], atol=1e-9)
    # Each combination step is Dempster's rule: check the last one against evidencelib.
    if k >= 2:
        wae = {s: float(v) for s, v in zip(focal, result.wae, strict=True) if v > 1e-9}
        step = dict(wae)
        for _ in range(k - 1):
            step = dict(_mass_items(_oracle(step, wae)))
        for col, subset in enumerate(result.focal_sets):
            assert result.fused[col] == pytest.approx(step.get(subset, 0.0), abs=1e-6)


def _mass_items(mass):
    for prop, value in mass.items():
        atoms = frozenset(a for a in ATOMS if (prop & FRAME.atom(a)) == FRAME.atom(a))
        yield atoms, value
