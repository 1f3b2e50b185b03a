"""The one SplitMix64 of the project (:mod:`amuled_ma.tasks.rng`) against published values.

The expected outputs are the test vectors of Vigna's reference ``splitmix64.c`` (state
1234567: 6457827717110365317, 3203168211198807973, ...; state 0: 0xE220A8397B1DCDAF) and a
plain-Python SplitMix64 on unsigned integers written out here.
"""

from __future__ import annotations

import torch

from amuled_ma.tasks import rng

MASK64 = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15


def reference_splitmix64(state: int) -> int:
    """``next()`` of ``splitmix64.c`` on the state ``state`` (unsigned Python integers)."""
    z = (state + GOLDEN) & MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK64
    return z ^ (z >> 31)


def test_splitmix64_matches_the_published_vectors():
    vectors = [
        6457827717110365317,
        3203168211198807973,
        9817491932198370423,
        4593380528125082431,
        16408922859458223821,
    ]
    state = 1234567
    for expected in vectors:
        assert rng.splitmix64(state) == expected
        state = (state + GOLDEN) & MASK64
    assert rng.splitmix64(0) == 0xE220A8397B1DCDAF


def test_splitmix64_of_large_and_wrapping_states():
    for state in (1, 2**63 - 1, 2**63, 2**64 - 1, 2**64 + 5, 3**50):
        assert rng.splitmix64(state) == reference_splitmix64(state)


def test_draws_are_the_finaliser_of_key_plus_counter_times_gamma():
    keys = rng.copy_keys(7, 4, torch.device("cpu"))
    unsigned = [k & MASK64 for k in keys.tolist()]
    got = rng.draws(keys, 10, 3)
    for i, key in enumerate(unsigned):
        for j in range(3):
            # mix64(key + c * GAMMA) is the SplitMix64 output of state key + (c - 1) * GAMMA
            expected = reference_splitmix64((key + (10 + j - 1) * GOLDEN) & MASK64)
            assert got[i, j].item() & MASK64 == expected
    counters = torch.tensor([0, 5, 9, 2])
    many = rng.draws(keys, counters, 2)
    for j in range(2):
        assert torch.equal(many[:, j], rng.draw(keys, counters, j))


def test_copy_keys_are_per_copy_seeds():
    keys = rng.copy_keys(40, 3, torch.device("cpu"))
    for i in range(3):
        assert torch.equal(keys[i : i + 1], rng.copy_keys(40 + i, 1, torch.device("cpu")))


def test_shift_right_and_uniform53():
    values = [-1, -(2**63), 2**63 - 1, 12345, -987654321]
    z = torch.tensor(values, dtype=torch.int64)
    for shift in (11, 30, 32, 63):
        expected = [(v & MASK64) >> shift for v in values]
        assert rng.shift_right(z, shift).tolist() == expected
    u = rng.uniform53(z).tolist()
    assert u == [((v & MASK64) >> 11) / 2.0**53 for v in values]
    assert all(0.0 <= x < 1.0 for x in u)
    assert rng.threshold32(0.5) == 2**31 and rng.threshold32(1.0) == 2**32
