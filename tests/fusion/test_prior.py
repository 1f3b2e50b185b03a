"""A prior on the members of the ``bjs-dst`` fusion: ``w_i ∝ rho_i · Crd_i · IV_i``.

Checked against numbers from outside the vectorised code: a plain loop implementation
written here (BJS, credibility, Deng entropy, information volume, Dempster's rule k - 1
times), hand-computed limits (a prior on one member alone is that member's belief raised to
the power k; a prior that undoes the credibility averages the beliefs), and the fusion
without a prior, bit for bit, on every state of the authors' recordings.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pytest

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.deliberation.panel import MoralPanel
from amuled_ma.fusion import RULES, fuse, register_rule, unregister_rule, xiao_fusion

RECORDINGS = [
    "findmilk-gpt-4o-mini.json",
    "findmilk-llama-3_1-70b.json",
    "findmilk-llama-3_1-8b.json",
    "findmilk-mistral-nemo.json",
    "driving-llama-3_1-70b.json",
]


def loop_fusion(beliefs: Sequence[Sequence[float]], prior: Sequence[float]) -> list[float]:
    """Xiao (2019) with a member prior, one state, plain loops (independent of the package)."""
    k, n = len(beliefs), len(beliefs[0])

    def bjs(p: Sequence[float], q: Sequence[float]) -> float:
        total = 0.0
        for a in range(n):
            mid = (p[a] + q[a]) / 2
            if p[a] > 0:
                total += 0.5 * p[a] * math.log2(p[a] / mid)
            if q[a] > 0:
                total += 0.5 * q[a] * math.log2(q[a] / mid)
        return total

    distance = [sum(bjs(beliefs[i], beliefs[j]) for j in range(k) if j != i) / (k - 1)
                for i in range(k)]  # fmt: skip
    support = [1.0 / d for d in distance]
    credibility = [s / sum(support) for s in support]
    entropy = [-sum(p * math.log2(p) for p in row if p > 0) for row in beliefs]
    volume = [math.exp(e) for e in entropy]
    volume = [v / sum(volume) for v in volume]
    adjusted = [c * v * r for c, v, r in zip(credibility, volume, prior, strict=True)]
    weights = [a / sum(adjusted) for a in adjusted]
    wae = [sum(weights[i] * beliefs[i][a] for i in range(k)) for a in range(n)]
    fused = list(wae)
    for _ in range(k - 1):  # Dempster's rule: singletons meet only themselves
        joint = [fused[a] * wae[a] for a in range(n)]
        fused = [j / sum(joint) for j in joint]
    return fused


HAND = np.array(
    [
        [0.70, 0.10, 0.10, 0.10],
        [0.60, 0.20, 0.10, 0.10],
        [0.80, 0.05, 0.05, 0.10],
        [0.10, 0.10, 0.10, 0.70],
        [0.65, 0.15, 0.10, 0.10],
    ]
)
RHO = np.array([0.4, 0.3, 0.15, 0.1, 0.05])


def test_the_prior_against_a_loop_implementation_by_hand():
    expected = loop_fusion(HAND.tolist(), RHO.tolist())
    np.testing.assert_allclose(fuse(HAND, prior=RHO), expected, rtol=0, atol=1e-12)
    # the prior shifts the fusion: the outlier (member 3) weighs less, action 0 more
    assert fuse(HAND, prior=[0.05, 0.05, 0.05, 0.8, 0.05])[3] > fuse(HAND)[3] + 0.1


def test_the_prior_on_random_batches_against_the_loops():
    rng = np.random.default_rng(11)
    beliefs = rng.dirichlet(np.ones(4), size=(40, 5))
    priors = rng.dirichlet(np.ones(5), size=40)
    fused = fuse(beliefs, prior=priors)  # one batched call, one prior per state
    for b, p, f in zip(beliefs, priors, fused, strict=True):
        np.testing.assert_allclose(f, loop_fusion(b.tolist(), p.tolist()), rtol=0, atol=1e-12)


def test_a_prior_on_one_member_gives_its_belief_to_the_power_k():
    # w = (1, 0, 0): WAE = m_1, and Dempster's rule twice gives m_1^3 / sum(m_1^3)
    m = np.array([[0.5, 0.3, 0.2], [0.1, 0.1, 0.8], [0.3, 0.3, 0.4]])
    cube = np.array([0.125, 0.027, 0.008]) / 0.16  # 0.5^3, 0.3^3, 0.2^3 and their sum
    np.testing.assert_allclose(fuse(m, prior=[1, 0, 0]), cube, rtol=0, atol=1e-15)
    result = fuse(m, prior=[2.0, 0, 0], return_diagnostics=True)  # any scale
    np.testing.assert_allclose(result.weights, [1, 0, 0], atol=1e-15)


def test_a_prior_that_undoes_the_credibility_averages_the_beliefs():
    w0 = fuse(HAND, return_diagnostics=True).weights
    mean = HAND.mean(axis=0)
    np.testing.assert_allclose(
        fuse(HAND, prior=1.0 / w0), mean**5 / (mean**5).sum(), rtol=0, atol=1e-14
    )


def test_a_uniform_prior_is_the_paper_s_fusion_bit_for_bit_by_hand():
    for prior in ([1, 1, 1, 1, 1], np.full(5, 0.2), [7.5] * 5):
        assert np.array_equal(fuse(HAND, prior=prior), fuse(HAND))
        with_prior = fuse(HAND, prior=prior, return_diagnostics=True)
        without = fuse(HAND, return_diagnostics=True)
        for key in ("weights", "credibility", "entropy", "conflicts", "wae"):
            assert np.array_equal(getattr(with_prior, key), getattr(without, key)), key


@pytest.mark.parametrize("name", RECORDINGS)
def test_a_uniform_prior_is_bit_for_bit_on_every_recorded_state(load_recording, name):
    recording = load_recording(name)
    clusters = recording["clusters"]
    beliefs = np.array([[s["beliefs"][c] for c in clusters] for s in recording["states"]])
    plain = fuse(beliefs)
    assert np.array_equal(fuse(beliefs, prior=np.full(5, 0.2)), plain)
    assert np.array_equal(fuse(beliefs, prior=np.ones((len(beliefs), 5))), plain)
    # a real prior on real beliefs, against the loops (states where the five differ and
    # every divergence is positive, where the loop's formula is defined)
    rng = np.random.default_rng(5)
    rows = [
        i for i in rng.permutation(len(beliefs))[:60] if len({b.tobytes() for b in beliefs[i]}) == 5
    ]
    fused = fuse(beliefs[rows], prior=RHO)
    for i, f in zip(rows, fused, strict=True):
        np.testing.assert_allclose(f, loop_fusion(beliefs[i].tolist(), RHO), rtol=0, atol=1e-12)


def test_the_general_xiao_fusion_takes_the_same_prior():
    sets = [{"up"}, {"down"}, {"left"}, {"right"}]
    general = xiao_fusion(HAND, sets, prior=RHO, closed_form=False)
    np.testing.assert_allclose(general.fused, fuse(HAND, prior=RHO), rtol=0, atol=1e-13)
    np.testing.assert_allclose(
        general.weights, fuse(HAND, prior=RHO, return_diagnostics=True).weights
    )


def test_identical_beliefs_with_a_prior_keep_the_documented_limit():
    m = np.array([0.5, 0.3, 0.2])
    same = np.stack([m] * 3)
    limit = m**3 / (m**3).sum()
    np.testing.assert_allclose(fuse(same, prior=[0.7, 0.2, 0.1]), limit, atol=1e-15)
    # the prior is 0 for every member... but one: the limit still holds
    np.testing.assert_allclose(fuse(same, prior=[0, 0, 1]), limit, atol=1e-15)


def test_a_bad_prior_is_refused_in_one_line():
    with pytest.raises(ValueError, match="takes no prior") as info:
        fuse(HAND, "mean", prior=RHO)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="prior must be finite and non-negative"):
        fuse(HAND, prior=[1, -1, 1, 1, 1])
    with pytest.raises(ValueError, match="are all zero"):
        fuse(HAND, prior=[0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="prior of shape"):
        fuse(HAND, prior=[1, 1])


def test_a_registered_rule_without_takes_prior_is_called_as_before():
    @register_rule("first-only")
    def first_only(beliefs, *, weights, param, diagnostics):
        return beliefs[..., 0, :].copy()

    try:
        assert not RULES["first-only"].takes_prior and RULES["bjs-dst"].takes_prior
        np.testing.assert_array_equal(fuse(HAND, "first-only"), HAND[0])
        with pytest.raises(ValueError, match="takes no prior"):
            fuse(HAND, "first-only", prior=RHO)
    finally:
        unregister_rule("first-only")


class Answers(BeliefSource):
    """Fixed answers; the agents in ``absent`` abstain."""

    name = "answers"
    needs_messages = False

    def __init__(self, absent: Sequence[str] = ()) -> None:
        self.absent = set(absent)

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        rows = dict(zip("abcde", HAND, strict=True))
        return [
            BeliefResult(np.full(4, 0.25), "abstained", self.name)
            if r.cluster in self.absent
            else BeliefResult(rows[r.cluster], "ok", self.name)
            for r in requests
        ]


def test_the_panel_fuses_with_the_prior_of_the_members_that_answered():
    names = list("abcde")
    panel = MoralPanel(
        "findmilk", names, Answers(["b"]), action_names=("u", "d", "l", "r"), prior=RHO
    )
    out = panel.fused(np.zeros((2, 8)))
    rows = [0, 2, 3, 4]
    expected = loop_fusion(HAND[rows].tolist(), RHO[rows].tolist())
    np.testing.assert_allclose(out.fused[0], expected, rtol=0, atol=1e-12)
    assert out.weights[0, 1] == 0.0 and out.weights[0].sum() == pytest.approx(1.0)
    # without the prior, the panel is the paper's fusion of the four
    plain = MoralPanel("findmilk", names, Answers(["b"]), action_names=("u", "d", "l", "r"))
    np.testing.assert_allclose(plain.fused(np.zeros((1, 8))).fused[0], fuse(HAND[rows]), atol=1e-15)
    with pytest.raises(ValueError, match="prior has 2 weights for 5 clusters"):
        MoralPanel("findmilk", names, Answers(), action_names=("u", "d", "l", "r"), prior=[1, 1])
