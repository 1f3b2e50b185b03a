"""Rules for acting under moral uncertainty: ``mec``, ``nash-vote``, ``variance-vote``, ``borda``.

A member is a theory of credence ``c_i`` (its weight or prior) and choiceworthiness ``b_i(a)``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from amuled_ma.fusion.rules import _generic_diagnostics, register_rule
from amuled_ma.fusion.xiao import FusionResult

__all__ = ["FLAT_SIGMA", "credences"]

FLAT_SIGMA = 1e-9
"""A belief with standard deviation at most this is flat: ``variance-vote`` gives it ``z = 0``."""


def credences(
    beliefs: np.ndarray, weights: np.ndarray | None, prior: np.ndarray | None
) -> np.ndarray:
    """Each member's credence ``c_i = w_i / sum_j w_j`` ``(..., k)`` (uniform without either).

    Raises ValueError: both ``weights`` and ``prior`` are given.
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


#: A rule's computation: beliefs ``(..., k, n)`` and credences ``(..., k)`` to the fused
#: belief ``(..., n)`` and each member's share of its mass ``(..., k)`` (the diagnostics' weights).
CredenceRule = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def _credence_rule(name: str) -> Callable[[CredenceRule], CredenceRule]:
    """Register ``name`` as a rule taking weights or a prior as the members' `credences`."""

    def decorator(compute: CredenceRule) -> CredenceRule:
        @functools.wraps(compute)
        def rule(
            beliefs: np.ndarray,
            *,
            weights: np.ndarray | None,
            param: str | None,
            diagnostics: bool,
            prior: np.ndarray | None = None,
        ) -> np.ndarray | FusionResult:
            fused, share = compute(beliefs, credences(beliefs, weights, prior))
            return _generic_diagnostics(beliefs, fused, share, name) if diagnostics else fused

        register_rule(name, takes_weights=True, takes_prior=True)(rule)
        return compute

    return decorator


@_credence_rule("mec")
def _mec_rule(beliefs: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximise expected choiceworthiness (MacAskill & Ord 2020): sum_i c_i b_i."""
    fused = (c[..., :, None] * beliefs).sum(axis=-2)
    fused = fused / fused.sum(axis=-1, keepdims=True)
    return fused, c


@_credence_rule("nash-vote")
def _nash_vote_rule(beliefs: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nash voting (Ecoffet & Lehman 2021): the vote shares of its one-state equilibrium.

    Every voter's dominant strategy puts its whole budget on its argmax (split among ties).
    """
    top = (beliefs == beliefs.max(axis=-1, keepdims=True)).astype(np.float64)
    allocation = top / top.sum(axis=-1, keepdims=True)  # each voter's budget share per action
    # votes = sum_i c_i v_i (freeform_voter.py NashEnv.step), p(a) = votes(a) / sum(votes)
    fused = (c[..., :, None] * allocation).sum(axis=-2)
    fused = fused / fused.sum(axis=-1, keepdims=True)
    return fused, c


@_credence_rule("variance-vote")
def _variance_vote_rule(beliefs: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Variance voting (Cotton-Barratt, MacAskill & Ord 2020; Ecoffet & Lehman 2021).

    ``sigma_i`` is the state's own (not averaged over visited states), so a state's reward
    does not depend on the states it was fused with.
    """
    centred = beliefs - beliefs.mean(axis=-1, keepdims=True)
    sigma = np.sqrt((centred**2).mean(axis=-1, keepdims=True))  # np.std(b_i), ddof = 0
    flat = sigma <= FLAT_SIGMA
    # z_i = (b_i - mean b_i) / sigma_i (Cotton-Barratt et al. 2020; VarianceModel.predict)
    z = np.where(flat, 0.0, centred / np.where(flat, 1.0, sigma))
    # fused(a) ∝ sum_i c_i (z_i(a) - min z_i): their stochastic variant (scores -= min)
    part = c[..., :, None] * (z - z.min(axis=-1, keepdims=True))
    votes = part.sum(axis=-2)
    total = votes.sum(axis=-1, keepdims=True)
    n = beliefs.shape[-1]
    fused = np.where(total > 0, votes / np.where(total > 0, total, 1.0), 1.0 / n)
    share = np.where(total > 0, part.sum(axis=-1) / np.where(total > 0, total, 1.0), c)
    return fused, share


@_credence_rule("borda")
def _borda_rule(beliefs: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Credence-weighted Borda count (MacAskill 2016) of the members' rankings of the actions."""
    n = beliefs.shape[-1]
    if n == 1:
        return np.ones((*beliefs.shape[:-2], 1)), c
    mine, other = beliefs[..., :, None], beliefs[..., None, :]  # (..., k, a, b)
    below = (other < mine).sum(axis=-1)
    equal = (other == mine).sum(axis=-1) - 1  # the action itself excluded
    points = below + 0.5 * equal  # s_i(a) = #{b_i(b) < b_i(a)} + ties / 2; sums to n(n-1)/2
    # credence-weighted Borda (MacAskill 2016): sum_i c_i s_i(a) / (n (n - 1) / 2)
    fused = (c[..., :, None] * points).sum(axis=-2) / (n * (n - 1) / 2)
    fused = fused / fused.sum(axis=-1, keepdims=True)
    return fused, c
