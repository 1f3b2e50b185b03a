"""Fusion rules by name: ``fuse(beliefs, rule)`` and the registry behind it.

## Description

A fusion rule turns the beliefs of ``k`` moral clusters over ``n`` actions, shape
``(..., k, n)``, into one belief ``(..., n)`` per leading (batch) index. Every rule is a
function registered by name with :func:`register_rule`; :func:`fuse` validates the input,
looks the rule up and calls it once for the whole batch.

## Rules

- ``"bjs-dst"``: Xiao (2019) BJS divergence + Deng-entropy weighting + Dempster's rule
  (see :mod:`amuled_ma.fusion.xiao`), the AMULED arbiter. Closed form
  ``WAE^k / sum(WAE^k)`` for beliefs over actions (singleton focal elements). Takes an
  optional member ``prior`` that multiplies Xiao's credibility (learned from people by
  ``amuled study fit-weights``); no prior is the paper's rule, bit for bit.
- ``"mean"``: weighted average ``sum_i w_i m_i / sum_i w_i`` (``weights`` default 1).
  This is the paper's "weight_average" baseline.
- ``"max"``: per-action maximum over clusters, renormalised:
  ``max_i m_i(a) / sum_b max_i m_i(b)`` (the paper's "arg_max" baseline; the authors'
  code skipped the renormalisation, we follow the paper's equation).
- ``"vote"``: each cluster votes for its most believed action; the action(s) with the
  most votes get the mass. **Ties**: a cluster whose belief has several equal maxima
  splits its vote equally among them; when several actions tie for the most votes
  (within ``1e-9`` of the total), the fused mass is split equally among them, e.g.
  ``[0.5, 0.5, 0, 0]``. This keeps ``vote`` symmetric in actions and clusters (the
  authors' code took the lowest index instead). ``weights`` scale the votes.
- ``"single:<i>"``: cluster ``i``'s own belief (``i`` may be negative, Python style): the
  per-cluster ablation.
- ``"mec"``, ``"nash-vote"``, ``"variance-vote"``, ``"borda"``: the rules for acting under
  moral uncertainty, the members' ``weights`` or ``prior`` as credences
  (:mod:`amuled_ma.fusion.moral_uncertainty`).

## Degenerate inputs

Invalid rows (NaN/inf, negative, sum not within ``1e-6`` of 1) raise ``ValueError`` naming
the index, e.g. ``beliefs[3, 2]``; valid rows are rescaled to sum to 1 when one is off by
more than ``1e-12`` (rows that already sum to 1 to rounding are used bit for bit). An empty
batch (a leading dimension of size 0) returns an empty result. See
:mod:`amuled_ma.fusion.xiao` for identical beliefs, ``k = 1``, zeros and total conflict.

## Writing a rule

```python
@register_rule("geometric")
def geometric(beliefs, *, weights, param, diagnostics):
    g = np.exp(np.log(beliefs + 1e-12).mean(axis=-2))
    return g / g.sum(axis=-1, keepdims=True)
```

A rule receives the validated float64 ``beliefs`` ``(..., k, n)`` and the keywords
``weights`` (``(..., k)`` or ``None``), ``param`` (the text after ``:`` in the rule name,
or ``None``) and ``diagnostics`` (bool); a rule registered with ``takes_prior=True`` also
receives ``prior`` (``(..., k)`` or ``None``). It returns the fused ``(..., n)`` array, or a
:class:`~amuled_ma.fusion.xiao.FusionResult`. When diagnostics are requested and a rule
returns a plain array, :func:`fuse` adds generic ones: uniform ``weights``, Xiao's
``credibility`` and ``entropy`` of the inputs, and no ``conflicts``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Literal, overload

import numpy as np
import numpy.typing as npt

from amuled_ma.fusion._validate import check_rows, check_weights
from amuled_ma.fusion.xiao import FusionResult, _measures, bjs_dst, check_prior
from amuled_ma.scenario.panel_checks import allow_fusion_rule, forget_fusion_rule

__all__ = ["RULES", "RuleSpec", "fuse", "register_rule", "unregister_rule"]

VOTE_TIE_TOLERANCE = 1e-9
"""Actions whose vote totals are within this fraction of all votes of the top tie."""

RuleFunc = Callable[..., "np.ndarray | FusionResult"]


@dataclass(frozen=True)
class RuleSpec:
    """A registered fusion rule.

    Attributes:
        name: the name used in ``fuse(..., rule=name)`` (before any ``:param``).
        func: the rule function (see the module docstring for its contract).
        takes_weights: whether the rule accepts ``weights``.
        takes_param: whether the rule needs a ``:param`` suffix (``"single:2"``).
        summary: first line of the function's docstring.
        takes_prior: whether the rule accepts a member ``prior`` (``bjs-dst``).

    """

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
    """Register the decorated function as the fusion rule ``name``.

    Args:
        name: the rule's name (no ``:``).
        takes_weights: the rule accepts per-cluster ``weights``; otherwise passing
            weights to it is an error.
        takes_param: the rule is selected as ``"name:<param>"`` and needs the param.
        replace: allow replacing an existing rule of that name.
        takes_prior: the rule accepts a member ``prior`` (it is then called with the
            keyword ``prior``, a validated ``(..., k)`` array or None); otherwise passing
            a prior to it is an error.

    Returns:
        The decorator; it returns the function unchanged.

    Raises:
        ValueError: bad name, or the name is taken and ``replace`` is false.

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
    """Remove a registered rule (mainly for tests and plug-in reloads).

    Raises:
        KeyError: no rule of that name.

    """
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
    k = beliefs.shape[-2]
    if weights is None:
        weights = np.full(beliefs.shape[:-1], 1.0 / k)
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


@overload
def fuse(
    beliefs: npt.ArrayLike,
    rule: str = ...,
    *,
    weights: npt.ArrayLike | None = ...,
    prior: npt.ArrayLike | None = ...,
    return_diagnostics: bool,
) -> np.ndarray | FusionResult: ...


def fuse(
    beliefs: npt.ArrayLike,
    rule: str = "bjs-dst",
    *,
    weights: npt.ArrayLike | None = None,
    prior: npt.ArrayLike | None = None,
    return_diagnostics: bool = False,
) -> np.ndarray | FusionResult:
    """Fuse the beliefs of ``k`` moral clusters into one belief over the actions.

    Args:
        beliefs: array-like ``(..., k, n)``: per leading index, ``k`` probability vectors
            over ``n`` actions (non-negative, summing to 1 within ``1e-6``). Leading
            dimensions are batch dimensions, fused in one vectorized call.
        rule: a registered rule name: ``"bjs-dst"`` (default), ``"mean"``, ``"max"``,
            ``"vote"``, ``"single:<i>"``, ``"mec"``, ``"nash-vote"``, ``"variance-vote"``,
            ``"borda"``, or one added with :func:`register_rule`.
        weights: optional per-cluster weights, broadcastable to ``(..., k)``
            (the rules with ``takes_weights``: all but ``bjs-dst``, ``max`` and
            ``single``); non-negative, not all zero.
        prior: optional prior reliability ``rho`` of each cluster, broadcastable to
            ``(..., k)`` (the rules with ``takes_prior``: ``bjs-dst`` and the
            moral-uncertainty rules, which take it as the credences); non-negative, not
            all zero, any scale. For ``bjs-dst`` it multiplies Xiao's adjusted
            credibility, ``w_i ∝ rho_i · Crd_i · IV_i`` (``docs/fusion.md``, "A prior on
            the members"). None, or a prior equal for every cluster, gives the paper's
            fusion bit for bit.
        return_diagnostics: return a :class:`~amuled_ma.fusion.xiao.FusionResult` with
            ``fused`` and ``weights``, ``credibility``, ``entropy`` ``(..., k)`` and
            ``conflicts`` ``(..., k - 1)`` (``bjs-dst``; empty for other rules).

    Returns:
        The fused beliefs ``(..., n)`` (float64, each a probability vector), or a
        ``FusionResult`` when ``return_diagnostics`` is true.

    Raises:
        ValueError: unknown rule; weights or a prior given to a rule that takes none;
            a bad prior (negative, all zero, wrong shape); bad shape; a row
            with NaN/inf or a negative entry or that does not sum to 1 (the message names
            the index, e.g. ``beliefs[7, 2]``).

    Example:
        Five clusters judge four actions (up, down, left, right); the fourth cluster is
        an outlier and gets the least weight:

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

        A batch of 1000 states is one call:

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


# ---------------------------------------------------------------------------------------
# Built-in rules


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
    """Majority vote of the clusters' argmax actions; ties split equally (see module doc)."""
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
