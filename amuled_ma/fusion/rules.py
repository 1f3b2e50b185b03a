"""Fusion rules by name: ``fuse(beliefs, rule)`` and the registry behind it (docs/fusion.md)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Literal, overload

import numpy as np
import numpy.typing as npt

from amuled_ma.fusion.xiao import (
    FusionResult,
    _measures,
    bjs_dst,
    check_prior,
    check_rows,
    check_weights,
)
from amuled_ma.scenario.panel_checks import allow_fusion_rule, forget_fusion_rule

__all__ = ["RULES", "RuleSpec", "fuse", "register_rule", "unregister_rule"]

VOTE_TIE_TOLERANCE = 1e-9
"""Actions whose vote totals are within this fraction of all votes of the top tie."""

RuleFunc = Callable[..., "np.ndarray | FusionResult"]


@dataclass(frozen=True)
class RuleSpec:
    """A registered fusion rule; ``summary`` is the first line of ``func``'s docstring."""

    name: str
    func: RuleFunc
    takes_weights: bool = False
    takes_param: bool = False
    summary: str = ""
    takes_prior: bool = False


_REGISTRY: dict[str, RuleSpec] = {}
RULES: Mapping[str, RuleSpec] = MappingProxyType(_REGISTRY)
"""Read-only view of the registered rules, by name."""


def register_rule(
    name: str,
    *,
    takes_weights: bool = False,
    takes_param: bool = False,
    replace: bool = False,
    takes_prior: bool = False,
) -> Callable[[RuleFunc], RuleFunc]:
    """Register the decorated function as the fusion rule ``name`` (docs/fusion.md).

    Raises ValueError: bad name, or the name is taken and ``replace`` is false.
    """
    if not name or ":" in name or name != name.strip():
        raise ValueError(f"rule name {name!r} must be non-empty, without ':' or spaces around")

    def decorator(func: RuleFunc) -> RuleFunc:
        if name in _REGISTRY and not replace:
            raise ValueError(f"fusion rule {name!r} is already registered (pass replace=True)")
        summary = (func.__doc__ or "").strip().splitlines()[0] if func.__doc__ else ""
        _REGISTRY[name] = RuleSpec(name, func, takes_weights, takes_param, summary, takes_prior)
        allow_fusion_rule(name, takes_param, takes_prior)  # a scenario may name it now
        return func

    return decorator


def unregister_rule(name: str) -> None:
    """Remove a registered rule; raises ``KeyError`` when none has that name."""
    del _REGISTRY[name]
    forget_fusion_rule(name)


def _lookup(rule: str) -> tuple[RuleSpec, str | None]:
    if not isinstance(rule, str):
        raise ValueError(f"rule must be a name such as 'bjs-dst', got {rule!r}")
    name, sep, param = rule.partition(":")
    spec = _REGISTRY.get(name)
    if spec is None:
        known = ", ".join(sorted(f"{n}:<param>" if s.takes_param else n for n, s in RULES.items()))
        raise ValueError(f"unknown fusion rule {rule!r}; registered rules: {known}")
    if spec.takes_param and not (sep and param):
        raise ValueError(f"fusion rule {name!r} needs a parameter, e.g. '{name}:0'")
    if not spec.takes_param and sep:
        raise ValueError(f"fusion rule {name!r} takes no parameter, got {rule!r}")
    return spec, (param if sep else None)


def _generic_diagnostics(
    beliefs: np.ndarray, fused: np.ndarray, weights: np.ndarray | None, rule: str
) -> FusionResult:
    if weights is None:
        weights = np.full(beliefs.shape[:-1], 1.0 / beliefs.shape[-2])
    credibility, entropy = _measures(beliefs)
    return FusionResult(
        fused=fused,
        weights=weights,
        credibility=credibility,
        entropy=entropy,
        conflicts=np.zeros((*beliefs.shape[:-2], 0)),
        rule=rule,
    )


@overload
def fuse(
    beliefs: npt.ArrayLike,
    rule: str = ...,
    *,
    weights: npt.ArrayLike | None = ...,
    prior: npt.ArrayLike | None = ...,
    return_diagnostics: Literal[False] = ...,
) -> np.ndarray: ...


@overload
def fuse(
    beliefs: npt.ArrayLike,
    rule: str = ...,
    *,
    weights: npt.ArrayLike | None = ...,
    prior: npt.ArrayLike | None = ...,
    return_diagnostics: Literal[True],
) -> FusionResult: ...


def fuse(
    beliefs: npt.ArrayLike,
    rule: str = "bjs-dst",
    *,
    weights: npt.ArrayLike | None = None,
    prior: npt.ArrayLike | None = None,
    return_diagnostics: bool = False,
) -> np.ndarray | FusionResult:
    """Fuse the beliefs ``(..., k, n)`` of ``k`` moral clusters into one belief ``(..., n)``.

    Args:
        beliefs: per leading (batch) index, ``k`` probability vectors over ``n`` actions.
        rule: a name in `RULES`, e.g. ``"bjs-dst"``, ``"mean"``, ``"single:<i>"``.
        weights: per-cluster weights broadcastable to ``(..., k)`` (rules with
            ``takes_weights``); non-negative, not all zero.
        prior: member reliability ``rho`` broadcastable to ``(..., k)``, any scale (rules
            with ``takes_prior``); for ``bjs-dst`` ``w_i ∝ rho_i · Crd_i · IV_i``. None or
            a constant prior gives the paper's fusion bit for bit.
        return_diagnostics: return a `FusionResult` instead of the fused array.

    Raises:
        ValueError: unknown rule; weights or a prior to a rule that takes none; a bad
            prior or shape; a row that is not a probability vector (names its index).

    Example:
        Five clusters judge four actions; the fourth, an outlier, gets the least weight:

        >>> import numpy as np
        >>> beliefs = np.array([
        ...     [0.70, 0.10, 0.10, 0.10],
        ...     [0.60, 0.20, 0.10, 0.10],
        ...     [0.80, 0.05, 0.05, 0.10],
        ...     [0.10, 0.10, 0.10, 0.70],
        ...     [0.65, 0.15, 0.10, 0.10],
        ... ])
        >>> np.round(fuse(beliefs), 4).tolist()
        [0.999, 0.0005, 0.0001, 0.0005]
        >>> np.round(fuse(beliefs, "mean"), 4).tolist()
        [0.57, 0.12, 0.09, 0.22]
        >>> fuse(beliefs, "vote").tolist()
        [1.0, 0.0, 0.0, 0.0]
        >>> fuse(beliefs, "single:3").tolist()
        [0.1, 0.1, 0.1, 0.7]
        >>> result = fuse(beliefs, return_diagnostics=True)
        >>> int(np.argmin(result.weights)), result.conflicts.shape
        (3, (4,))
        >>> fuse(np.broadcast_to(beliefs, (1000, 5, 4))).shape
        (1000, 4)
    """
    spec, param = _lookup(rule)
    m = check_rows(beliefs, "beliefs")
    if m.shape[-2] == 0:
        raise ValueError(f"beliefs must hold at least one cluster, got shape {m.shape}")
    w = None
    if weights is not None:
        if not spec.takes_weights:
            raise ValueError(f"fusion rule {rule!r} takes no weights")
        w = check_weights(weights, m.shape[:-1])
    extra: dict[str, Any] = {}
    if prior is not None:
        if not spec.takes_prior:
            raise ValueError(
                f"fusion rule {rule!r} takes no prior: a member prior multiplies Xiao's "
                "credibility, use rule 'bjs-dst'"
            )
        extra["prior"] = check_prior(prior, m.shape[:-1])
    elif spec.takes_prior:
        extra["prior"] = None
    out = spec.func(m, weights=w, param=param, diagnostics=return_diagnostics, **extra)
    fused = out.fused if isinstance(out, FusionResult) else out
    if fused.shape != m.shape[:-2] + m.shape[-1:]:
        raise ValueError(
            f"fusion rule {rule!r} returned shape {fused.shape}, expected "
            f"{m.shape[:-2] + m.shape[-1:]}"
        )
    if not return_diagnostics:
        return fused
    if isinstance(out, FusionResult):
        return out
    return _generic_diagnostics(m, out, None, rule)


def _share(fused: np.ndarray, contribution: np.ndarray) -> np.ndarray:
    """Each cluster's share of the fused mass: ``sum_a fused_a * c_ia / sum_j c_ja``."""
    total = contribution.sum(axis=-2, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        part = np.where(total > 0, contribution / np.where(total > 0, total, 1.0), 0.0)
    return (part * fused[..., None, :]).sum(axis=-1)


@register_rule("bjs-dst", takes_prior=True)
def _bjs_dst_rule(beliefs, *, weights, param, diagnostics, prior=None):
    """Xiao (2019) BJS divergence + belief entropy + Dempster's rule (AMULED)."""
    return bjs_dst(beliefs, diagnostics, prior)


@register_rule("mean", takes_weights=True)
def _mean_rule(beliefs, *, weights, param, diagnostics):
    """Weighted average of the clusters' beliefs (weights default to 1)."""
    k = beliefs.shape[-2]
    w = np.full(beliefs.shape[:-1], 1.0 / k) if weights is None else weights
    w = w / w.sum(axis=-1, keepdims=True)
    fused = (w[..., :, None] * beliefs).sum(axis=-2)
    fused = fused / fused.sum(axis=-1, keepdims=True)
    if not diagnostics:
        return fused
    return _generic_diagnostics(beliefs, fused, np.array(w), "mean")


@register_rule("max")
def _max_rule(beliefs, *, weights, param, diagnostics):
    """Per-action maximum over clusters, renormalised to a probability vector."""
    top = beliefs.max(axis=-2)
    fused = top / top.sum(axis=-1, keepdims=True)
    if not diagnostics:
        return fused
    holds_max = (beliefs == top[..., None, :]).astype(np.float64)
    return _generic_diagnostics(beliefs, fused, _share(fused, holds_max), "max")


@register_rule("vote", takes_weights=True)
def _vote_rule(beliefs, *, weights, param, diagnostics):
    """Majority vote of the clusters' argmax actions; tied actions share the mass equally."""
    is_top = (beliefs == beliefs.max(axis=-1, keepdims=True)).astype(np.float64)
    votes = is_top / is_top.sum(axis=-1, keepdims=True)
    if weights is not None:
        votes = votes * weights[..., None]
    tally = votes.sum(axis=-2)
    best = tally.max(axis=-1, keepdims=True)
    winners = (tally >= best - VOTE_TIE_TOLERANCE * tally.sum(axis=-1, keepdims=True)) & (tally > 0)
    fused = winners / winners.sum(axis=-1, keepdims=True)
    if not diagnostics:
        return fused
    return _generic_diagnostics(beliefs, fused, _share(fused, votes), "vote")


@register_rule("single", takes_param=True)
def _single_rule(beliefs, *, weights, param, diagnostics):
    """One cluster's own belief, ``single:<i>`` (the per-cluster ablation)."""
    k = beliefs.shape[-2]
    try:
        index = int(param)
    except (TypeError, ValueError):
        raise ValueError(f"'single:{param}': the cluster index must be an integer") from None
    if not -k <= index < k:
        raise ValueError(f"'single:{param}': cluster index out of range for {k} clusters")
    fused = beliefs[..., index, :].copy()
    if not diagnostics:
        return fused
    onehot = np.zeros(beliefs.shape[:-1])
    onehot[..., index] = 1.0
    return _generic_diagnostics(beliefs, fused, onehot, f"single:{param}")
