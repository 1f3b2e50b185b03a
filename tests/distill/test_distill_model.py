"""The distilled model: valid beliefs, deterministic refits, and it learns what it is shown."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from amuled_ma.beliefs.replies.validate import validate_belief
from amuled_ma.distill import EnsembleModel, FitSettings

torch.set_num_threads(1)

MEMBERS = ("care", "virtue")


def data(n: int = 40, seed: int = 0):
    """States on a line; care prefers action 0 left of 0 and action 1 right of it."""
    rng = np.random.default_rng(seed)
    obs = np.stack([rng.uniform(-3, 3, n), rng.uniform(0, 1, n)], axis=1)
    care = np.where(obs[:, :1] < 0, [0.85, 0.05, 0.05, 0.05], [0.05, 0.85, 0.05, 0.05])
    virtue = np.tile([0.25, 0.25, 0.25, 0.25], (n, 1))
    return obs, np.stack([care, virtue], axis=1), np.ones((n, 2), dtype=bool)


def fitted(seed: int = 3, **kwargs) -> EnsembleModel:
    model = EnsembleModel(MEMBERS, 4, FitSettings(**kwargs))
    model.fit(*data(), seed=seed)
    return model


def test_answers_are_valid_beliefs_by_the_package_rule():
    model = fitted()
    far = np.array([[-1e4, 5.0], [0.0, 0.0], [1e4, -3.0]])  # also far outside the data
    for per_member in model.predict(far):
        for belief in per_member:
            validate_belief(belief.tolist(), 4, where="distilled model")  # raises if invalid
            assert (belief >= 0).all() and abs(belief.sum() - 1) <= 1e-12
    ensemble = model.predict_ensemble(far)
    assert ensemble.shape == (5, 3, 2, 4) and np.allclose(ensemble.sum(-1), 1, atol=1e-12)


def test_refits_are_bit_identical_given_the_seed_and_differ_for_another():
    probe = np.linspace(-3, 3, 11)[:, None].repeat(2, axis=1)
    first, again, other = fitted(seed=3), fitted(seed=3), fitted(seed=4)
    assert np.array_equal(first.predict_ensemble(probe), again.predict_ensemble(probe))
    assert not np.array_equal(first.predict_ensemble(probe), other.predict_ensemble(probe))


def test_the_global_torch_rng_is_left_alone():
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    fitted()
    assert torch.equal(torch.rand(3), expected)


def test_it_learns_the_members_beliefs():
    model = fitted(ensemble=3)
    left, right = model.predict(np.array([[-2.0, 0.5], [2.0, 0.5]]))
    assert left[0].argmax() == 0 and right[0].argmax() == 1  # care
    assert np.abs(left[1] - 0.25).max() < 0.1  # virtue is uniform everywhere


def test_a_member_without_answers_is_not_trained():
    obs, beliefs, mask = data()
    mask[:, 1] = False
    model = EnsembleModel(MEMBERS, 4)
    model.fit(obs, beliefs, mask, seed=1)
    assert model.trained.tolist() == [True, False]


def test_fitting_works_inside_the_learners_inference_mode():
    with torch.inference_mode():
        model = fitted(ensemble=2, steps=30)
    assert model.fitted


def test_shapes_are_checked():
    obs, beliefs, mask = data()
    with pytest.raises(ValueError, match="members"):
        EnsembleModel(("care",), 4).fit(obs, beliefs, mask, seed=1)
    with pytest.raises(RuntimeError, match="never fitted"):
        EnsembleModel(MEMBERS, 4).predict(obs)
