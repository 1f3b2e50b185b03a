"""The moral-uncertainty rules: mec, nash-vote, variance-vote, borda.

Exact values are computed by hand in the comments; the reference checks port the formulas of
Ecoffet & Lehman's code (github.com/uber-research/normative-uncertainty, commit 1f9e09d,
``freeform_voter.py``) line by line and compare.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.stats import rankdata

from amuled_ma.fusion import RULES, fuse

NEW_RULES = ["mec", "nash-vote", "variance-vote", "borda"]

# Three members over four actions (the test_fusion_rules panel).
B = np.array(
    [
        [0.70, 0.10, 0.10, 0.10],
        [0.60, 0.20, 0.10, 0.10],
        [0.10, 0.10, 0.10, 0.70],
    ]
)


def test_registered_with_credences_as_weights_or_prior():
    for name in NEW_RULES:
        spec = RULES[name]
        assert spec.takes_weights and spec.takes_prior and not spec.takes_param
    with pytest.raises(ValueError, match="credences once"):
        fuse(B, "borda", weights=[1, 2, 1], prior=[1, 2, 3])


# --- mec -------------------------------------------------------------------------------


def test_mec_by_hand_and_equal_to_weighted_mean():
    # credences (1, 3, 0) / 4: 0.25 * b1 + 0.75 * b2 = (0.175 + 0.45, 0.025 + 0.15, 0.1, 0.1)
    np.testing.assert_allclose(
        fuse(B, "mec", prior=[1, 3, 0]), [0.625, 0.175, 0.1, 0.1], atol=1e-15
    )
    # uniform: (1.4 / 3, 0.4 / 3, 0.3 / 3, 0.9 / 3)
    np.testing.assert_allclose(fuse(B, "mec"), [1.4 / 3, 0.4 / 3, 0.1, 0.3], atol=1e-15)
    # the same numbers as "mean" with the credences as weights, bit for bit
    c = np.array([0.2, 0.5, 0.3])
    np.testing.assert_array_equal(fuse(B, "mec", prior=c), fuse(B, "mean", weights=c))
    np.testing.assert_array_equal(fuse(B, "mec", weights=c), fuse(B, "mec", prior=c))


# --- nash-vote -------------------------------------------------------------------------


def test_nash_vote_by_hand():
    # favourites: a0, a0, a3; uniform credence 1/3 each -> (2/3, 0, 0, 1/3)
    np.testing.assert_allclose(fuse(B, "nash-vote"), [2 / 3, 0, 0, 1 / 3], atol=1e-15)
    # credences (2, 1, 1) / 4 -> a0: 0.5 + 0.25, a3: 0.25
    np.testing.assert_allclose(fuse(B, "nash-vote", prior=[2, 1, 1]), [0.75, 0, 0, 0.25])
    # a voter tied between a0 and a1 splits its budget: (1/2 * 1/2 + 1/2, 1/2 * 1/2, 0, 0)
    tied = np.array([[0.4, 0.4, 0.1, 0.1], [1.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(fuse(tied, "nash-vote"), [0.75, 0.25, 0, 0], atol=1e-15)
    # "vote" gives the winner everything; nash-vote keeps the minority's share
    np.testing.assert_array_equal(fuse(B, "vote"), [1, 0, 0, 0])


def _their_nash_step(raw, credences, budget=10.0, cost_exponent=1):
    """One step of ``NashEnv.step`` (freeform_voter.py:206-228) with stochastic voting.

    The default budget is ``self.default_budget = 10.0`` (:189) and ``cost_exponent=1`` the
    default of ``train_trolley`` (:698). Returns the outcome distribution ``votes``.
    """
    actions = np.exp(np.array(raw, dtype=np.float64))  # :209
    for i in range(len(actions)):
        cost_paid = np.sum(np.abs(actions[i]) ** cost_exponent)  # :211
        if cost_paid > budget:  # :214-215
            actions[i] *= (budget / cost_paid) ** (1 / cost_exponent)
    votes = np.sum(actions * np.asarray(credences)[:, None], axis=0)  # :222
    votes += 0.000001  # :227
    votes /= np.sum(votes)  # :228
    return votes


def _all_in(belief, budget=10.0):
    """Raw votes (before exp) putting the whole budget on the belief's maxima, shared."""
    top = belief == belief.max()
    return np.where(top, np.log(budget / top.sum()), -300.0)


def test_nash_vote_is_the_outcome_of_their_step_when_every_voter_goes_all_in():
    tied = np.array([[0.4, 0.4, 0.1, 0.1], [0.1, 0.2, 0.3, 0.4], [0.0, 0.0, 0.5, 0.5]])
    for beliefs, c in [(B, [0.2, 0.5, 0.3]), (tied, [0.5, 0.25, 0.25])]:
        theirs = _their_nash_step([_all_in(b) for b in beliefs], c)
        np.testing.assert_allclose(fuse(beliefs, "nash-vote", prior=c), theirs, atol=1e-5)


def test_all_in_on_the_favourite_is_each_voters_best_response_in_their_step():
    """The dominant strategy the closed form rests on, checked with their outcome function."""
    rng = np.random.default_rng(7)
    c = np.array([0.2, 0.5, 0.3])
    for _ in range(60):
        others = [np.log(rng.dirichlet(np.ones(4)) * rng.uniform(0.1, 10)) for _ in B]
        for i, belief in enumerate(B):
            profile = list(others)
            profile[i] = _all_in(belief)
            best = _their_nash_step(profile, c) @ belief
            for _ in range(5):  # any other allocation, any spend up to the budget
                profile[i] = np.log(rng.dirichlet(np.ones(4)) * rng.uniform(0.01, 10))
                assert _their_nash_step(profile, c) @ belief <= best + 1e-6


# --- variance-vote ---------------------------------------------------------------------


def test_variance_vote_by_hand():
    # b1 = (1, 0, 0, 0): centred (3/4, -1/4, -1/4, -1/4), variance (9 + 3) / 64 = 3/16,
    #   sigma = sqrt(3)/4, z = (sqrt(3), -1/sqrt(3), ...), z - min z = (4/sqrt(3), 0, 0, 0)
    # b2 = (0.4, 0.4, 0.1, 0.1): centred (.15, .15, -.15, -.15), sigma = .15,
    #   z = (1, 1, -1, -1), z - min z = (2, 2, 0, 0)
    # credences 1/2: votes ∝ (4/sqrt(3) + 2, 2, 0, 0); times sqrt(3)/2: (2 + sqrt(3), sqrt(3))
    beliefs = np.array([[1.0, 0.0, 0.0, 0.0], [0.4, 0.4, 0.1, 0.1]])
    r3 = math.sqrt(3)
    want = np.array([2 + r3, r3, 0, 0]) / (2 + 2 * r3)
    np.testing.assert_allclose(fuse(beliefs, "variance-vote"), want, atol=1e-15)
    # mean would be (0.7, 0.2, 0.05, 0.05); nash-vote (0.75, 0.25, 0, 0)
    diag = fuse(beliefs, "variance-vote", return_diagnostics=True)
    # each member's share of the mass: (4/sqrt(3)) / (4/sqrt(3) + 4) = 1 / (1 + sqrt(3))
    np.testing.assert_allclose(diag.weights, [1 / (1 + r3), r3 / (1 + r3)], atol=1e-15)


def test_variance_vote_ignores_each_members_scale_unlike_mean():
    # (0.3, 0.3, 0.2, 0.2) = 1/4 + (1/3) * ((0.4, 0.4, 0.1, 0.1) - 1/4): the same z
    strong = np.array([[0.4, 0.4, 0.1, 0.1], [0.1, 0.1, 0.1, 0.7]])
    weak = np.array([[0.3, 0.3, 0.2, 0.2], [0.1, 0.1, 0.1, 0.7]])
    np.testing.assert_allclose(
        fuse(weak, "variance-vote"), fuse(strong, "variance-vote"), atol=1e-15
    )
    assert not np.allclose(fuse(weak, "mean"), fuse(strong, "mean"))


def test_variance_vote_flat_members_add_nothing_and_all_flat_is_uniform():
    flat = np.full(4, 0.25)
    one = np.array([0.5, 0.3, 0.1, 0.1])
    # one member alone: (b - min b) / sum = (0.4, 0.2, 0, 0) / 0.6
    np.testing.assert_allclose(fuse(one[None], "variance-vote"), [2 / 3, 1 / 3, 0, 0])
    np.testing.assert_allclose(
        fuse(np.stack([flat, one]), "variance-vote"), [2 / 3, 1 / 3, 0, 0], atol=1e-15
    )
    np.testing.assert_array_equal(fuse(np.stack([flat, flat]), "variance-vote"), flat)
    # two actions: z = +-1, so variance-vote is nash-vote
    two = np.array([[0.9, 0.1], [0.4, 0.6], [0.7, 0.3]])
    np.testing.assert_allclose(fuse(two, "variance-vote"), fuse(two, "nash-vote"), atol=1e-15)


def _their_variance_votes(action_scores, credences, do_variance=True, stochastic=True):
    """``VarianceModel.predict`` (freeform_voter.py:508-521) for one state.

    ``stds`` is each theory's ``np.std`` over the actions of this state (:512); their code
    averages it over the visited states (``RollingMeanOfStd``, :383-391), ours is per state.
    """
    stds = np.array([np.std(a) for a in action_scores])  # :512
    if do_variance:  # :515-516
        normalized_scores = (action_scores - np.mean(action_scores, axis=1)[:, None]) / (
            stds[:, None] + 0.000001
        )
    else:
        normalized_scores = action_scores.copy()  # :518
    if stochastic:
        normalized_scores -= np.min(normalized_scores, axis=1)[:, None]  # :520
    return np.sum(normalized_scores * np.asarray(credences)[:, None], axis=0)  # :521


def test_variance_vote_and_mec_reproduce_their_predict():
    rng = np.random.default_rng(3)
    for beliefs in [B, rng.dirichlet(np.ones(5), size=4), rng.dirichlet(np.ones(3), size=2)]:
        c = rng.dirichlet(np.ones(len(beliefs)))
        votes = _their_variance_votes(beliefs, c)
        ours = fuse(beliefs, "variance-vote", prior=c)
        np.testing.assert_allclose(ours, votes / votes.sum(), atol=1e-5)
        assert np.argmax(ours) == np.argmax(votes)
        mec = _their_variance_votes(beliefs, c, do_variance=False, stochastic=False)
        np.testing.assert_allclose(fuse(beliefs, "mec", prior=c), mec, atol=1e-15)


# --- borda -----------------------------------------------------------------------------


def test_borda_by_hand():
    # points s_i(a) = below + ties / 2:
    # b1 (.7, .1, .1, .1): (3, 1, 1, 1); b2 (.6, .2, .1, .1): (3, 2, .5, .5);
    # b3 (.1, .1, .1, .7): (1, 1, 1, 3); sum (7, 4, 2.5, 4.5), / 3 members / 6 points
    np.testing.assert_allclose(fuse(B, "borda"), [7 / 18, 4 / 18, 5 / 36, 9 / 36], atol=1e-15)
    # credences (1, 0, 1) / 2: (4, 2, 2, 4) / 2 / 6
    np.testing.assert_allclose(fuse(B, "borda", prior=[1, 0, 1]), [1 / 3, 1 / 6, 1 / 6, 1 / 3])
    # one action: [1]; a flat member gives every action (n - 1) / 2 points
    np.testing.assert_array_equal(fuse(np.ones((3, 1)), "borda"), [1.0])
    np.testing.assert_allclose(fuse(np.full((2, 4), 0.25), "borda"), np.full(4, 0.25))


def test_borda_points_are_scipys_average_ranks_minus_one():
    """``s_i(a)`` is ``rankdata(b_i, "average") - 1`` (ties share their ranks' mean)."""
    rng = np.random.default_rng(5)
    beliefs = rng.choice([0.1, 0.2, 0.3], size=(4, 6))  # many ties
    beliefs /= beliefs.sum(axis=-1, keepdims=True)
    c = rng.dirichlet(np.ones(4))
    points = np.array([rankdata(b, method="average") - 1 for b in beliefs])
    np.testing.assert_allclose(
        fuse(beliefs, "borda", prior=c), c @ points / (6 * 5 / 2), atol=1e-15
    )


def test_borda_uses_only_the_ranking():
    # the same order, other numbers: the same result (mec differs)
    other = np.array([[0.4, 0.2, 0.2, 0.2], [0.9, 0.05, 0.025, 0.025], [0.2, 0.2, 0.2, 0.4]])
    np.testing.assert_allclose(fuse(other, "borda"), fuse(B, "borda"), atol=1e-15)
    assert not np.allclose(fuse(other, "mec"), fuse(B, "mec"))


# --- every rule ------------------------------------------------------------------------


@pytest.mark.parametrize("rule", NEW_RULES)
def test_a_member_of_credence_zero_is_a_member_left_out(rule):
    np.testing.assert_allclose(
        fuse(B, rule, prior=[2, 0, 1]), fuse(B[[0, 2]], rule, prior=[2, 1]), atol=1e-15
    )


@pytest.mark.parametrize("rule", NEW_RULES)
def test_degenerate_panels(rule):
    onehot = np.array([[0.0, 1.0, 0.0]])
    assert np.argmax(fuse(onehot, rule)) == 1
    assert fuse(np.zeros((0, 3, 4)), rule).shape == (0, 4)
    batch = np.stack([B, B[::-1], B[[1, 0, 2]]])
    np.testing.assert_allclose(fuse(batch, rule), [fuse(s, rule) for s in batch], atol=1e-15)
    diag = fuse(batch, rule, return_diagnostics=True)
    np.testing.assert_allclose(diag.weights.sum(axis=-1), 1.0)


@st.composite
def belief_matrices(draw, max_clusters=6, max_actions=5):
    k = draw(st.integers(1, max_clusters))
    n = draw(st.integers(1, max_actions))
    raw = draw(
        arrays(
            np.float64,
            (draw(st.integers(1, 3)), k, n),
            elements=st.one_of(st.just(0.0), st.floats(1e-6, 1.0), st.sampled_from([0.1, 0.5])),
        )
    )
    raw[..., 0] += (raw.sum(axis=-1) == 0).astype(float)
    return raw / raw.sum(axis=-1, keepdims=True)


@settings(max_examples=40, deadline=None)
@given(belief_matrices(), st.sampled_from(NEW_RULES), st.randoms())
def test_properties(beliefs, rule, rnd):
    out = fuse(beliefs, rule)
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    np.testing.assert_allclose(out.sum(axis=-1), 1.0, atol=1e-12)
    order = list(range(beliefs.shape[-2]))
    rnd.shuffle(order)
    np.testing.assert_allclose(fuse(beliefs[:, order], rule), out, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(belief_matrices(max_clusters=1), st.integers(1, 5), st.sampled_from(NEW_RULES))
def test_a_unanimous_panel_keeps_the_argmax(one, k, rule):
    belief = one[0, 0]
    out = fuse(np.broadcast_to(belief, (k, belief.size)), rule)
    assert belief[np.argmax(out)] >= belief.max() - 1e-12  # a top action wins
    assert np.all(out[belief == belief.max()] >= out.max() - 1e-12)  # every top action does


# --- in a scenario -----------------------------------------------------------------------


def test_a_scenario_may_weigh_the_members_of_a_moral_uncertainty_rule(tmp_path):
    """``[feedback].weights`` with ``fusion = "mec"``: accepted, the credences of the panel."""
    from amuled_ma.deliberation.plan import plan_panel
    from amuled_ma.files.resources import scenarios_dir
    from amuled_ma.scenario import PAPER_CLUSTERS, load_scenario

    weights = {"care": 2.0, "virtue": 1.0, "consequentialist": 4.0, "deontological": 2.0,
               "social_justice": 1.0}  # fmt: skip
    (tmp_path / "w.json").write_text(
        json.dumps({"members": list(weights), "weights": list(weights.values())})
    )
    text = (scenarios_dir() / "findmilk.toml").read_text()
    text = text.replace('source = "replay"', 'source = "rules"', 1)
    text = text.replace('fusion = "bjs-dst"', 'fusion = "mec"\nweights = "w.json"')
    (tmp_path / "findmilk.toml").write_text(text)
    plan = plan_panel("amuled", load_scenario(tmp_path / "findmilk.toml"))
    assert plan.rule == "mec"
    # credences w / sum(w), sum 10, in the panel's order
    assert plan.prior == pytest.approx([weights[c] / 10 for c in PAPER_CLUSTERS], abs=1e-15)


# --- on the authors' recordings ------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "agree", "top"),
    [  # docs/reproduction.md's table: same top action as bjs-dst, mean max_a fused[a]
        (
            "findmilk-gpt-4o-mini.json",
            {"mec": 0.960, "nash-vote": 0.996, "variance-vote": 0.977, "borda": 0.969},
            {"mec": 0.647, "nash-vote": 0.829, "variance-vote": 0.695, "borda": 0.460},
        ),
        (
            "driving-llama-3_1-70b.json",
            {"mec": 0.973, "nash-vote": 0.994, "variance-vote": 0.991, "borda": 0.992},
            {"mec": 0.734, "nash-vote": 0.846, "variance-vote": 0.774, "borda": 0.598},
        ),
    ],
)
def test_every_recorded_state(load_recording, name, agree, top):
    """Each rule on the five clusters' beliefs of every state the authors recorded."""
    recording = load_recording(name)
    clusters = recording["clusters"]
    beliefs = np.array([[s["beliefs"][c] for c in clusters] for s in recording["states"]])
    states = np.arange(len(beliefs))
    best = fuse(beliefs, "bjs-dst").argmax(axis=-1)
    # nash-vote, counted here from each cluster's favourites: the share of the panel whose
    # argmax (ties split) is the action
    favourite = beliefs == beliefs.max(axis=-1, keepdims=True)
    shares = (favourite / favourite.sum(axis=-1, keepdims=True)).mean(axis=-2)
    np.testing.assert_allclose(fuse(beliefs, "nash-vote"), shares, atol=1e-12)
    # uniform credences: mec is the plain mean of the five beliefs
    np.testing.assert_allclose(fuse(beliefs, "mec"), beliefs.mean(axis=-2), atol=1e-12)
    for rule in NEW_RULES:
        fused = fuse(beliefs, rule)
        same = np.isclose(fused[states, best], fused.max(axis=-1))  # bjs-dst's is a top one
        assert round(float(same.mean()), 3) == agree[rule], rule
        assert round(float(fused.max(axis=-1).mean()), 3) == top[rule], rule
