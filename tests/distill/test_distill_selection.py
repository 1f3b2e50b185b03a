"""Selection: disagreement by hand, novelty picks a far state over a duplicate, seeded random."""

from __future__ import annotations

import numpy as np

from amuled_ma.distill import choose_random, choose_uncertain, disagreement


def test_disagreement_is_the_mean_total_variation_to_the_ensemble_mean():
    # two networks, one state, one member: [1, 0] and [0, 1]; mean [0.5, 0.5]; TV 0.5 each
    predictions = np.array([[[[1.0, 0.0]]], [[[0.0, 1.0]]]])
    assert disagreement(predictions).tolist() == [0.5]
    # networks that agree: 0
    assert disagreement(np.array([[[[0.3, 0.7]]], [[[0.3, 0.7]]]])).tolist() == [0.0]
    # two members, only the second counted: TV of [0.2, 0.8] vs [0.6, 0.4] to [0.4, 0.6] = 0.2
    two = np.array([[[[1.0, 0.0], [0.2, 0.8]]], [[[0.0, 1.0], [0.6, 0.4]]]])
    assert np.allclose(disagreement(two, np.array([False, True])), [0.2])


def test_a_state_far_from_the_asked_ones_is_picked_over_a_duplicate():
    asked = np.array([[0.0, 0.0], [1.0, 0.0]])
    duplicate, far = [0.0, 0.0], [6.0, 5.0]
    candidates = np.array([duplicate, far])
    assert choose_uncertain(candidates, 1, asked) == [1]
    # also when the ensemble disagrees equally on both
    assert choose_uncertain(candidates, 1, asked, spread=np.array([0.3, 0.3])) == [1]
    # but a duplicate the ensemble is far more unsure about wins
    assert choose_uncertain(candidates, 1, asked, spread=np.array([1.0, 0.0])) == [0]


def test_one_batch_does_not_spend_its_share_on_near_duplicates():
    asked = np.zeros((0, 2))
    candidates = np.array([[0.0, 0.0], [0.0, 0.01], [5.0, 5.0]])
    first, second = choose_uncertain(candidates, 2, asked)
    assert {first, second} == {0, 2}  # after one of the twins, the far one is more novel


def test_before_anything_was_asked_every_state_is_equally_uncertain():
    assert choose_uncertain(np.array([[1.0], [2.0], [3.0]]), 1, np.zeros((0, 1))) == [0]


def test_random_selection_is_seeded():
    a = choose_random(20, 5, np.random.default_rng(1))
    b = choose_random(20, 5, np.random.default_rng(1))
    c = choose_random(20, 5, np.random.default_rng(2))
    assert a == b and a != c and len(set(a)) == 5
    assert choose_random(3, 10, np.random.default_rng(1)).__len__() == 3
