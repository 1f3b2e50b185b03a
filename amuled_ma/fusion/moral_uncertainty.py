"""Rules for acting under moral uncertainty: ``mec``, ``nash-vote``, ``variance-vote``, ``borda``.

## Description

The moral-uncertainty literature asks how an agent should act when its credence is split
across moral theories ``T_1..T_k``, each ranking or scoring the options. Its rules become
fusion rules here with one mapping, used by all four:

- a **theory** is a panel member (a moral cluster);
- its **credence** ``c_i`` is the member's weight, ``c_i = w_i / sum_j w_j``, where ``w`` is
  the ``prior`` the panel hands to the fusion (``[feedback].weights``) or ``weights``, and
  ``1/k`` each when neither is given; a member absent from a state has ``c_i = 0`` (the panel
  fuses only the members that answered, and every rule here gives the same result for a
  member of credence 0 as without it);
- its **choiceworthiness** of action ``a`` in a state is its belief, ``W_i(a) = b_i(a)``
  (the probability the member gives to ``a`` being the right action). Ecoffet & Lehman (2021)
  define it as theory ``i``'s action value ``Q_i(s, a)``, learned from the theory's own
  reward; a panel member has neither, and gives no score but its belief.

Each rule returns a probability vector per state, because the fine-tune's reward is
``fused[a]``; how each rule's scores become one is part of its definition below.

Sources: MacAskill & Ord (2020) "Why maximize expected choice-worthiness?", Nous 54(2):327-353
(MEC); MacAskill (2016) "Normative uncertainty as a voting problem", Mind 125(500):967-1004
(credence-weighted Borda); Cotton-Barratt, MacAskill & Ord (2020) "Statistical normalization
methods in interpersonal and intertheoretic comparisons", J. Philosophy 117(2):61-95
(variance normalisation); Ecoffet & Lehman (2021) "Reinforcement learning under moral
uncertainty", ICML, PMLR 139:2926-2936, and its code, github.com/uber-research/
normative-uncertainty, ``freeform_voter.py`` (``NashEnv.step``: Nash voting;
``VarianceModel.predict``: variance voting and MEC).

## Rules

- ``"mec"``: ``fused(a) = sum_i c_i b_i(a)``. With ``W_i = b_i`` this is ``"mean"`` with the
  credences as weights, value for value; it exists as a name of its own because it reads the
  panel's member prior as credences, which ``"mean"`` does not take.
- ``"nash-vote"``: each member is a voter with a budget ``c_i B``; the outcome is drawn in
  proportion to the votes (the code's ``stochastic_voting``) and a vote costs its size
  (``cost_exponent=1``, the code's default). Then ``fused(a) = sum_i c_i [a in argmax b_i]
  / |argmax b_i|``: the vote shares of the one equilibrium (derivation at the function).
- ``"variance-vote"``: each member's beliefs normalised to mean 0 and variance 1 over the
  actions of the state, ``z_i = (b_i - 1/n) / sigma_i``, credence-weighted summed,
  ``S(a) = sum_i c_i z_i(a)``, then shifted per member to a minimum of 0 and normalised:
  ``fused(a) ∝ sum_i c_i (z_i(a) - min_b z_i(b))``, i.e. ``S(a) - sum_i c_i min z_i``.
- ``"borda"``: ``fused(a) = sum_i c_i s_i(a) / (n(n-1)/2)``, ``s_i(a)`` the number of actions
  member ``i`` believes less in than ``a``, plus half the number it believes in equally.

## Degenerate inputs

One member: ``mec`` returns its belief, ``nash-vote`` its argmax (shared among ties),
``variance-vote`` ``(b - min b) / sum(b - min b)``, ``borda`` its normalised ranks. A flat
belief (``sigma_i <= FLAT_SIGMA``) has ``z_i = 0`` and adds nothing to ``variance-vote``;
when every member of positive credence is flat the result is uniform. One action: ``[1]``.
Ties between actions are exact float equality, as in ``"vote"``.
"""

from __future__ import annotations

import numpy as np

from amuled_ma.fusion.rules import _generic_diagnostics, register_rule
from amuled_ma.fusion.xiao import FusionResult

__all__ = ["FLAT_SIGMA", "credences"]

FLAT_SIGMA = 1e-9
"""A belief whose standard deviation over the actions is at most this is flat (indifferent):
``variance-vote`` gives it ``z = 0`` instead of dividing rounding noise up to unit variance."""


def credences(
    beliefs: np.ndarray, weights: np.ndarray | None, prior: np.ndarray | None
) -> np.ndarray:
    """Each member's credence, ``c_i = w_i / sum_j w_j`` ``(..., k)``; uniform by default.

    Args:
        beliefs: validated beliefs ``(..., k, n)`` (for the shape).
        weights: validated ``(..., k)`` weights, or None.
        prior: validated ``(..., k)`` member prior (the panel's ``[feedback].weights``), or None.

    Returns:
        Non-negative credences summing to 1 over the members.

    Raises:
        ValueError: both ``weights`` and ``prior`` are given (the credences are given once).

    """
    if weights is not None and prior is not None:
        raise ValueError(
            "give the members' credences once: weights or prior, not both (they are the same "
            "numbers to a moral-uncertainty rule)"
        )
    w = weights if weights is not None else prior
    if w is None:
        return np.full(beliefs.shape[:-1], 1.0 / beliefs.shape[-2])
    return w / w.sum(axis=-1, keepdims=True)


def _result(
    beliefs: np.ndarray, fused: np.ndarray, share: np.ndarray, rule: str, diagnostics: bool
) -> np.ndarray | FusionResult:
    """``fused``, or with diagnostics whose ``weights`` are each member's share of the mass."""
    if not diagnostics:
        return fused
    return _generic_diagnostics(beliefs, fused, share, rule)


@register_rule("mec", takes_weights=True, takes_prior=True)
def _mec_rule(
    beliefs: np.ndarray,
    *,
    weights: np.ndarray | None,
    param: str | None,
    diagnostics: bool,
    prior: np.ndarray | None = None,
) -> np.ndarray | FusionResult:
    """Maximise expected choiceworthiness (MacAskill & Ord 2020): sum_i c_i b_i."""
    c = credences(beliefs, weights, prior)
    # MEC: EC(a) = sum_i C(T_i) W_i(a), W_i = b_i (MacAskill & Ord 2020)
    fused = (c[..., :, None] * beliefs).sum(axis=-2)
    fused = fused / fused.sum(axis=-1, keepdims=True)
    return _result(beliefs, fused, c, "mec", diagnostics)


@register_rule("nash-vote", takes_weights=True, takes_prior=True)
def _nash_vote_rule(
    beliefs: np.ndarray,
    *,
    weights: np.ndarray | None,
    param: str | None,
    diagnostics: bool,
    prior: np.ndarray | None = None,
) -> np.ndarray | FusionResult:
    """Nash voting (Ecoffet & Lehman 2021), one state: the vote shares of its equilibrium.

    Voter ``i`` casts votes ``u_i(a) >= 0`` at cost ``sum_a |u_i(a)|^p`` from a budget ``B``
    (``p = cost_exponent = 1``, ``default_budget = 10``), weighted by its credence,
    ``V = sum_j c_j u_j`` (``NashEnv.step``); with ``v_i = c_i u_i`` that is a budget
    ``c_i B``, ``sum_a v_i(a) <= c_i B``. The action is drawn with probability
    ``p(a) = V(a) / sum_b V(b)`` (``stochastic_voting``). Spending more on one's most choiceworthy
    action raises its probability and lowers every other one's in proportion, so every
    voter spends its whole budget, ``sum_b V(b) = B``, and voter ``i``'s expected
    choiceworthiness ``sum_a p(a) b_i(a) = (1/B) sum_a v_i(a) b_i(a) + (others' part)`` is
    linear in its own votes: putting the whole budget on ``argmax b_i`` is its dominant
    strategy, whatever the others do. The equilibrium outcome is
    ``p(a) = sum_i c_i [a in argmax b_i] / |argmax b_i|`` (a voter indifferent among tied
    maxima splits its budget equally: any split is optimal for it, the equal one keeps the
    rule symmetric in actions). It needs no intertheoretic comparison of the beliefs'
    scales (only each member's argmax counts), Ecoffet & Lehman's reason for Nash voting.
    The budget is per state: the panel scores states one by one, so the paper's trade of
    budget across an episode's steps does not arise.
    """
    c = credences(beliefs, weights, prior)
    top = (beliefs == beliefs.max(axis=-1, keepdims=True)).astype(np.float64)
    allocation = top / top.sum(axis=-1, keepdims=True)  # each voter's budget share per action
    # votes = sum_i c_i v_i (freeform_voter.py NashEnv.step), p(a) = votes(a) / sum(votes)
    fused = (c[..., :, None] * allocation).sum(axis=-2)
    fused = fused / fused.sum(axis=-1, keepdims=True)
    return _result(beliefs, fused, c, "nash-vote", diagnostics)


@register_rule("variance-vote", takes_weights=True, takes_prior=True)
def _variance_vote_rule(
    beliefs: np.ndarray,
    *,
    weights: np.ndarray | None,
    param: str | None,
    diagnostics: bool,
    prior: np.ndarray | None = None,
) -> np.ndarray | FusionResult:
    """Variance voting (Cotton-Barratt, MacAskill & Ord 2020; Ecoffet & Lehman 2021).

    ``z_i(a) = (b_i(a) - mean_b b_i(b)) / sigma_i``, ``sigma_i`` the population standard
    deviation of ``b_i`` over the actions of the state (``np.std``, as
    ``VarianceModel.predict`` takes ``np.std`` of each theory's action scores), ``z_i = 0``
    for a flat belief (``sigma_i <= FLAT_SIGMA``). Ecoffet & Lehman average the variance over
    the states the policy visits, ``sigma_i = sqrt(E_s Var_a Q_i(s, a))``
    (``RollingMeanOfStd``); here it is the state's own: the panel memoises each state's fused
    belief and fuses states in groups of whoever answered them, so a variance over the batch
    would make a state's reward depend on the states it happened to be fused with
    (``docs/fusion.md``). Scores ``S(a) = sum_i c_i z_i(a)``; the probability vector is the
    code's stochastic variant (``normalized_scores -= min`` per theory, then the
    credence-weighted sum): ``fused(a) ∝ sum_i c_i (z_i(a) - min_b z_i(b))``, which has
    ``argmax S`` as its argmax and needs no temperature; uniform when every member of
    positive credence is flat.
    """
    c = credences(beliefs, weights, prior)
    centred = beliefs - beliefs.mean(axis=-1, keepdims=True)
    sigma = np.sqrt((centred**2).mean(axis=-1, keepdims=True))  # np.std(b_i), ddof = 0
    flat = sigma <= FLAT_SIGMA
    # z_i = (b_i - mean b_i) / sigma_i (Cotton-Barratt et al. 2020; VarianceModel.predict)
    z = np.where(flat, 0.0, centred / np.where(flat, 1.0, sigma))
    # c_i (z_i - min z_i): their stochastic variant (normalized_scores -= min, then * credences)
    part = c[..., :, None] * (z - z.min(axis=-1, keepdims=True))
    votes = part.sum(axis=-2)
    total = votes.sum(axis=-1, keepdims=True)
    n = beliefs.shape[-1]
    fused = np.where(total > 0, votes / np.where(total > 0, total, 1.0), 1.0 / n)
    if not diagnostics:
        return fused
    mass = part.sum(axis=-1)
    share = np.where(total > 0, mass / np.where(total > 0, total, 1.0), c)
    return _generic_diagnostics(beliefs, fused, share, "variance-vote")


@register_rule("borda", takes_weights=True, takes_prior=True)
def _borda_rule(
    beliefs: np.ndarray,
    *,
    weights: np.ndarray | None,
    param: str | None,
    diagnostics: bool,
    prior: np.ndarray | None = None,
) -> np.ndarray | FusionResult:
    """Credence-weighted Borda count (MacAskill 2016) of the members' rankings of the actions.

    ``s_i(a) = #{b: b_i(b) < b_i(a)} + #{b != a: b_i(b) = b_i(a)} / 2`` (tied actions share
    their ranks' points); MacAskill's Borda score, the number of options below ``a`` minus the
    number above, is ``2 s_i(a) - (n - 1)``, the same order. ``fused(a) = sum_i c_i s_i(a) /
    (n (n - 1) / 2)`` (each member's points sum to ``n (n - 1) / 2``); ``[1]`` when ``n = 1``.
    """
    c = credences(beliefs, weights, prior)
    n = beliefs.shape[-1]
    if n == 1:
        return _result(beliefs, np.ones((*beliefs.shape[:-2], 1)), c, "borda", diagnostics)
    mine, other = beliefs[..., :, None], beliefs[..., None, :]  # (..., k, a, b)
    below = (other < mine).sum(axis=-1)
    equal = (other == mine).sum(axis=-1) - 1  # the action itself excluded
    points = below + 0.5 * equal  # s_i(a); sums to n (n - 1) / 2 over a
    # credence-weighted Borda (MacAskill 2016): sum_i c_i s_i(a) / (n (n - 1) / 2)
    fused = (c[..., :, None] * points).sum(axis=-2) / (n * (n - 1) / 2)
    fused = fused / fused.sum(axis=-1, keepdims=True)
    return _result(beliefs, fused, c, "borda", diagnostics)
