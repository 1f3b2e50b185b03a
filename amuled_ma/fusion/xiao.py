"""Xiao (2019) evidence fusion, batched; docs/fusion.md: the steps and every degenerate input."""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "FusionResult",
    "bjs_divergence",
    "dempster_combine",
    "deng_entropy",
    "xiao_fusion",
]

FocalSets = tuple[frozenset, ...]

SUM_TOLERANCE = 1e-6
"""Largest accepted ``|sum(row) - 1|`` for a belief row or mass function."""

RESCALE_THRESHOLD = 1e-12
"""Rows are divided by their sums when some ``|sum(row) - 1|`` exceeds this (else used as is)."""


def _index_text(name: str, index: tuple[int, ...]) -> str:
    if not index:
        return name
    return f"{name}[{', '.join(str(int(i)) for i in index)}]"


def check_rows(values: object, name: str = "beliefs", *, min_ndim: int = 2) -> np.ndarray:
    """Return ``values`` (shape ``(..., n)``) as float64 rows rescaled to sum to 1 (read-only).

    Raises:
        ValueError: ``ndim < min_ndim``, an empty row, or a row with NaN/inf, a negative
            entry or a sum farther than `SUM_TOLERANCE` from 1 (names the row's index).
    """
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of numbers: {exc}") from None
    if array.ndim < min_ndim:
        raise ValueError(
            f"{name} must have at least {min_ndim} dimensions, got shape {array.shape}"
        )
    if array.shape[-1] == 0:
        raise ValueError(f"{name} must have at least one entry per row, got shape {array.shape}")
    if array.size == 0:
        return array
    # Fast path: three whole-array reductions. NaN/inf make a row sum non-finite, and a
    # NaN minimum or sum fails every comparison, so only bad input takes the slow path.
    sums = np.einsum("...i->...", array)
    lowest = array.min()
    if not (
        lowest >= 0 and sums.max() - 1.0 <= SUM_TOLERANCE and 1.0 - sums.min() <= SUM_TOLERANCE
    ):
        _raise_first_bad_row(array, sums, name)
    if max(sums.max() - 1.0, 1.0 - sums.min()) > RESCALE_THRESHOLD:
        array = array / sums[..., None]
    return array


def _raise_first_bad_row(array: np.ndarray, sums: np.ndarray, name: str) -> None:
    finite = np.asarray(np.isfinite(array).all(axis=-1))
    nonneg = np.asarray((array >= 0).all(axis=-1))
    close = np.abs(sums - 1.0) <= SUM_TOLERANCE
    good = finite & nonneg & close
    index = tuple(int(i) for i in np.argwhere(~good)[0])
    row = array[index]
    if not finite[index]:
        reason = "contains NaN or infinity"
    elif not nonneg[index]:
        reason = "has a negative entry"
    else:
        reason = f"sums to {float(sums[index])!r}, expected 1 within {SUM_TOLERANCE:g}"
    raise ValueError(
        f"{_index_text(name, index)} is not a probability vector: {reason} (got {row.tolist()})"
    )


def check_weights(
    weights: npt.ArrayLike, batch_shape: tuple[int, ...], name: str = "weights"
) -> np.ndarray:
    """Return per-cluster ``weights`` broadcast to ``batch_shape`` as float64.

    Raises ValueError: not broadcastable, NaN/inf, negative, or all zero for some leading index.
    """
    try:
        array = np.broadcast_to(np.asarray(weights, dtype=np.float64), batch_shape)
    except ValueError:
        shape = np.shape(weights)
        raise ValueError(
            f"{name} of shape {shape} do not broadcast to (..., n_clusters) = {batch_shape}"
        ) from None
    if array.size == 0:
        return array
    bad_entry = ~np.isfinite(array) | (array < 0)
    if bad_entry.any():
        index = tuple(int(i) for i in np.argwhere(bad_entry)[0])
        raise ValueError(
            f"{_index_text(name, index)} = {float(array[index])!r}: {name} must be "
            "finite and non-negative"
        )
    zero = array.sum(axis=-1) <= 0
    if zero.any():
        index = tuple(int(i) for i in np.argwhere(zero)[0])
        raise ValueError(
            f"{_index_text(name, index)} are all zero: at least one cluster needs weight"
        )
    return array


@dataclass(frozen=True, eq=False)
class FusionResult:
    """The fused masses ``(..., n)`` of one or many fusions, with the diagnostics that explain them.

    Attributes:
        fused: a probability vector per leading index, over ``focal_sets`` or the actions.
        weights: ``(..., k)`` each source's final weight (``bjs-dst``: ``w_i``; other rules:
            its share of the fused mass); sums to 1.
        credibility: ``(..., k)`` Xiao's ``Crd_i``.
        entropy: ``(..., k)`` Deng entropy of each source, in bits.
        conflicts: ``(..., k - 1)`` Dempster's ``K`` per combination (empty for other rules).
        focal_sets: the focal element of each column of ``fused`` (``xiao_fusion`` only).
        wae: ``(..., n)`` the weighted average evidence (``bjs-dst`` only).
        rule: the name of the rule that produced the result.
    """

    fused: np.ndarray
    weights: np.ndarray
    credibility: np.ndarray
    entropy: np.ndarray
    conflicts: np.ndarray
    focal_sets: FocalSets | None = None
    wae: np.ndarray | None = None
    rule: str = "bjs-dst"


def _xlog2x(m: np.ndarray) -> np.ndarray:
    """``m * log2(m)`` element-wise with ``0 log 0 = 0``."""
    return m * np.log2(np.where(m > 0, m, 1.0))


def bjs_divergence(m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """Belief Jensen-Shannon divergence (Xiao 2019, eq. 8), log2, over the last axis, in [0, 1]."""
    a = np.asarray(m1, dtype=np.float64)
    b = np.asarray(m2, dtype=np.float64)
    s = a + b
    terms = _xlog2x(a) + _xlog2x(b) - s * (np.log2(np.where(s > 0, s, 1.0)) - 1.0)
    value = 0.5 * terms.sum(axis=-1)
    return np.where(np.all(a == b, axis=-1), 0.0, np.maximum(value, 0.0))


def _log2_capacity(focal_sets: FocalSets | None) -> np.ndarray | None:
    """``log2(2^|A| - 1)`` per focal element, or None when all are singletons."""
    if focal_sets is None:
        return None
    sizes = np.array([len(a) for a in focal_sets], dtype=np.float64)
    if np.all(sizes == 1):
        return None
    # log2(2^c - 1) = c + log2(1 - 2^-c), stable for large c.
    return sizes + np.log2(-np.expm1(-sizes * np.log(2.0)))


def deng_entropy(
    masses: np.ndarray, focal_sets: Iterable[Iterable[Hashable]] | None = None
) -> np.ndarray:
    """Deng entropy ``E_d(m) = -sum_A m(A) log2(m(A) / (2^|A| - 1))`` in bits, over the last axis.

    ``focal_sets`` None means singletons (Shannon entropy); ``masses`` are not validated.
    """
    m = np.asarray(masses, dtype=np.float64)
    cap = _log2_capacity(None if focal_sets is None else _as_focal_sets(focal_sets))
    value = -_xlog2x(m).sum(axis=-1)
    if cap is not None:
        value = value + (m * cap).sum(axis=-1)
    return value


# Internal layout: a batch (..., k, n) is transposed once to contiguous (k, n, B) "columns",
# so numpy works on long rows of length B (several times faster than small trailing axes).

_NEAR_ZERO_BJS = 1e-9  # pairs below this are compared element-wise for exact identity
_BLOCK = 4096  # states per block in bjs_dst: keeps the temporaries in the CPU cache
_TINY = 1e-300  # added before log2 so that 0 log 0 = 0 * log2(1e-300) = 0, never NaN


def _to_columns(m: np.ndarray) -> np.ndarray:
    """``(..., k, n)`` -> contiguous ``(k, n, B)``."""
    k, n = m.shape[-2:]
    flat = m.reshape(-1, k * n)
    return np.ascontiguousarray(flat.T).reshape(k, n, flat.shape[0])


def _from_columns(x: np.ndarray, batch: tuple[int, ...]) -> np.ndarray:
    """``(c, B)`` -> ``(*batch, c)``."""
    return np.ascontiguousarray(x.T).reshape(*batch, x.shape[0])


def _columns_credibility(bjs: np.ndarray) -> np.ndarray:
    """``Crd_i = (1/BJS_i) / sum_j (1/BJS_j)`` over axis 0; its limit where some are 0."""
    low = bjs.min(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        support = low / np.where(bjs > 0, bjs, 1.0)  # in (0, 1]: no overflow
    degenerate = ~(low > 0)
    if degenerate.any():  # some BJS_i == 0: share the credibility among those sources
        support[:, degenerate] = (bjs[:, degenerate] <= 0).astype(np.float64)
    return support / support.sum(axis=0)


def _columns_measures(t: np.ndarray, cap: np.ndarray | None):
    """Credibility ``(k, B)`` and Deng entropy ``(k, B)`` of columns ``t`` ``(k, n, B)``."""
    k = t.shape[0]
    floored = t + _TINY  # log2 argument > 0; changes sums of x log x by ~1e-297 at most
    xl = np.log2(floored)
    xl *= t  # exactly 0 where t == 0: 0 log 0 = 0
    neg_h = xl.sum(axis=1)  # sum_A m log2 m, per source
    rows = t.sum(axis=1)
    total = np.zeros(rows.shape)
    for i in range(k - 1):
        # BJS(m_i, m_j) for all j > i at once, with s = m_i + m_j:
        # 1/2 [sum m_i log2 m_i + sum m_j log2 m_j - sum s log2 s + sum s].
        s = floored[i] + floored[i + 1 :]
        s_log_s = np.log2(s)
        s_log_s *= s
        pair = neg_h[i] + neg_h[i + 1 :]
        pair -= s_log_s.sum(axis=1)
        pair += rows[i]
        pair += rows[i + 1 :]
        pair *= 0.5
        np.maximum(pair, 0.0, out=pair)
        # Identical rows have BJS exactly 0 (rounding leaves ~1e-16): test the few near 0.
        small = pair < _NEAR_ZERO_BJS
        if small.any():
            near, column = np.nonzero(small)
            same = (t[i][:, column] == t[i + 1 + near, :, column].T).all(axis=0)
            pair[near[same], column[same]] = 0.0
        total[i] += pair.sum(axis=0)
        total[i + 1 :] += pair
    credibility = _columns_credibility(total) if k > 1 else np.ones(rows.shape)
    entropy = -neg_h
    if cap is not None:
        entropy += (t * cap[None, :, None]).sum(axis=1)
    return credibility, entropy


def _columns_wae(t: np.ndarray, cap: np.ndarray | None, prior: np.ndarray | None = None):
    """Run steps 1-3 on columns: ``(wae (n, B), weights, credibility, entropy)``.

    ``prior`` ``(k, B)`` multiplies the adjusted credibility before it is normalised.
    """
    credibility, entropy = _columns_measures(t, cap)
    # exp(E - max E) / sum: the normalised information volume, safe from overflow.
    volume = np.exp(entropy - entropy.max(axis=0))
    adjusted = credibility * volume
    if prior is not None:
        adjusted = adjusted * prior
        total = adjusted.sum(axis=0)
        empty = ~(total > 0)
        if empty.any():  # the prior is 0 wherever the credibility is not (only possible
            # when some BJS_i are exactly 0): fall back to the prior times the volume
            adjusted[:, empty] = (prior * volume)[:, empty]
    weights = adjusted / adjusted.sum(axis=0)
    wae = weights[0] * t[0]
    for i in range(1, t.shape[0]):
        wae += weights[i] * t[i]
    return wae, weights, credibility, entropy


def _power(r: np.ndarray, k: int) -> np.ndarray:
    """``r ** k`` for an integer ``k >= 1`` by repeated squaring (faster than ``np.power``)."""
    base = r
    while not k & 1:
        base = base * base
        k >>= 1
    result = base.copy()
    k >>= 1
    while k:
        base = base * base
        if k & 1:
            result = result * base
        k >>= 1
    return result


def _columns_closed_form(wae: np.ndarray, k: int, diagnostics: bool):
    """Dempster's rule on singleton ``wae`` ``(n, B)`` with itself ``k - 1`` times."""
    top = wae.max(axis=0)
    r = wae / top  # max entry is 1: r**k never underflows to an all-zero row
    if not diagnostics:
        p = _power(r, k)
        return p / p.sum(axis=0), None
    # K_t = 1 - sum(WAE^{t+1}) / sum(WAE^t), t = 1..k-1 (sum(WAE) = 1 after validation).
    p = r
    sums = [p.sum(axis=0)]
    for _ in range(k - 1):
        p = p * r
        sums.append(p.sum(axis=0))
    fused = p / sums[-1]
    conflicts = np.empty((k - 1, wae.shape[1]))
    for t in range(k - 1):
        conflicts[t] = 1.0 - top * sums[t + 1] / sums[t]
    return fused, np.clip(conflicts, 0.0, 1.0)


def _prior_columns(prior: np.ndarray) -> np.ndarray:
    """A validated prior ``(..., k)`` (already broadcast to the batch) -> ``(k, B)``."""
    k = prior.shape[-1]
    return np.ascontiguousarray(prior.reshape(-1, k).T)


def _measures(m: np.ndarray, cap: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Xiao credibility and Deng entropy ``(..., k)`` of mass functions ``(..., k, n)``."""
    batch = m.shape[:-2]
    credibility, entropy = _columns_measures(_to_columns(m), cap)
    return _from_columns(credibility, batch), _from_columns(entropy, batch)


def _as_focal_sets(focal_sets: Iterable[Iterable[Hashable]]) -> FocalSets:
    result = []
    for position, item in enumerate(focal_sets):
        if isinstance(item, str | bytes):
            raise ValueError(
                f"focal_sets[{position}] = {item!r}: give a set of hypotheses, e.g. {{{item!r}}}"
            )
        subset = frozenset(item)
        if not subset:
            raise ValueError(f"focal_sets[{position}] is the empty set: it cannot carry mass")
        if subset in result:
            raise ValueError(f"focal_sets[{position}] = {set(subset)} is listed twice")
        result.append(subset)
    if not result:
        raise ValueError("focal_sets is empty")
    return tuple(result)


def _intersection_table(left: FocalSets, right: FocalSets, out: list[frozenset]):
    """Map each ``(left, right)`` pair to its intersection's column in ``out`` (extended)."""
    target = np.full(len(left) * len(right), -1)
    for p, a in enumerate(left):
        for q, b in enumerate(right):
            c = a & b
            if c:
                if c not in out:
                    out.append(c)
                target[p * len(right) + q] = out.index(c)
    table = np.zeros((target.size, len(out)))
    hit = target >= 0
    table[np.flatnonzero(hit), target[hit]] = 1.0
    return table, (~hit).astype(np.float64)


def _combine(m1: np.ndarray, m2: np.ndarray, table: np.ndarray, conflict_of: np.ndarray):
    """One batched Dempster combination; returns ``(masses, K)`` or raises at ``K = 1``."""
    outer = (m1[..., :, None] * m2[..., None, :]).reshape((*m1.shape[:-1], -1))
    joint = outer @ table
    conflict = outer @ conflict_of
    total = joint.sum(axis=-1)
    if np.any(total <= 0):
        index = tuple(int(i) for i in np.argwhere(total <= 0)[0])
        where = f" at batch index {index}" if index else ""
        raise ValueError(
            f"total conflict (K = 1){where}: Dempster's rule is undefined when no pair of "
            "focal elements with positive mass intersects"
        )
    return joint / total[..., None], np.clip(conflict, 0.0, 1.0)


def dempster_combine(
    m1: np.ndarray,
    focal_sets1: Iterable[Iterable[Hashable]],
    m2: np.ndarray,
    focal_sets2: Iterable[Iterable[Hashable]] | None = None,
) -> tuple[np.ndarray, FocalSets, np.ndarray]:
    """Dempster's rule ``m(C) = sum_{A ∩ B = C} m1(A) m2(B) / (1 - K)``, batched.

    Returns:
        ``(masses, focal_sets, K)``: masses ``(..., n)`` over ``focal_sets`` (``focal_sets1``,
        then the new sets of ``focal_sets2``, then new intersections in order of first
        appearance) and the conflict ``K = sum_{A ∩ B = ∅} m1(A) m2(B)`` of shape ``(...)``.

    Raises:
        ValueError: invalid masses or focal sets, or total conflict (``K = 1``).

    Example:
        >>> import numpy as np
        >>> m, sets, k = dempster_combine(
        ...     np.array([0.6, 0.4]), [{"a"}, {"a", "b"}], np.array([0.5, 0.5]), [{"b"}, {"a", "b"}]
        ... )
        >>> [sorted(s) for s in sets], np.round(m, 4).tolist(), float(k)
        ([['a'], ['a', 'b'], ['b']], [0.4286, 0.2857, 0.2857], 0.3)
    """
    sets1 = _as_focal_sets(focal_sets1)
    sets2 = sets1 if focal_sets2 is None else _as_focal_sets(focal_sets2)
    a = check_rows(m1, "m1", min_ndim=1)
    b = check_rows(m2, "m2", min_ndim=1)
    if a.shape[-1] != len(sets1) or b.shape[-1] != len(sets2):
        raise ValueError(
            f"m1 has {a.shape[-1]} masses for {len(sets1)} focal sets and m2 has "
            f"{b.shape[-1]} for {len(sets2)}: they must match"
        )
    out = list(sets1)
    for s in sets2:
        if s not in out:
            out.append(s)
    table, conflict_of = _intersection_table(sets1, sets2, out)
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    a = np.broadcast_to(a, shape + a.shape[-1:])
    b = np.broadcast_to(b, shape + b.shape[-1:])
    masses, conflict = _combine(a, b, table, conflict_of)
    return masses, tuple(out), conflict


def _general_self_combination(wae: np.ndarray, sets: FocalSets, k: int):
    """Combine ``wae`` (over ``sets``) with itself ``k - 1`` times by the general rule."""
    out = list(sets)
    # Close the focal elements under intersection, then build the table on the closure.
    grown = True
    while grown:
        before = len(out)
        _intersection_table(tuple(out), sets, out)
        grown = len(out) > before
    table, conflict_of = _intersection_table(tuple(out), sets, out)
    current = np.zeros((*wae.shape[:-1], len(out)))
    current[..., : len(sets)] = wae
    conflicts = []
    for _ in range(k - 1):
        current, conflict = _combine(current, wae, table, conflict_of)
        conflicts.append(conflict)
    stacked = np.stack(conflicts, axis=-1) if conflicts else np.zeros((*wae.shape[:-1], 0))
    return current, tuple(out), stacked


def xiao_fusion(
    masses: np.ndarray,
    focal_sets: Iterable[Iterable[Hashable]],
    *,
    closed_form: bool | None = None,
    prior: npt.ArrayLike | None = None,
) -> FusionResult:
    """Fuse ``k`` mass functions ``(..., k, n)`` over arbitrary ``focal_sets`` by Xiao (2019).

    Args:
        masses: ``k`` mass functions over the ``n`` ``focal_sets`` per leading index.
        focal_sets: ``n`` distinct non-empty sets of hypotheses (a string is rejected).
        closed_form: ``WAE^k / sum(WAE^k)``; None uses it exactly when every focal element
            is a singleton, False forces the general combination, True needs singletons.
        prior: per-source ``rho`` broadcastable to ``(..., k)``, ``w_i ∝ rho_i · Crd_i · IV_i``.

    Returns:
        A `FusionResult`; ``.focal_sets`` lists ``focal_sets`` then any new intersections.

    Raises:
        ValueError: bad shapes, invalid rows (the message names the index) or focal sets.

    Example:
        Xiao (2019)'s five-sensor example on the frame ``{A, B, C}``:

        >>> import numpy as np
        >>> masses = np.array([
        ...     [0.41, 0.29, 0.30, 0.00],
        ...     [0.00, 0.90, 0.10, 0.00],
        ...     [0.58, 0.07, 0.00, 0.35],
        ...     [0.55, 0.10, 0.00, 0.35],
        ...     [0.60, 0.10, 0.00, 0.30],
        ... ])
        >>> result = xiao_fusion(masses, [{"A"}, {"B"}, {"C"}, {"A", "C"}])
        >>> np.round(result.wae, 4).tolist()
        [0.5316, 0.1472, 0.0521, 0.2692]
        >>> np.round(result.fused, 4).tolist()
        [0.9895, 0.0002, 0.0061, 0.0043]
        >>> int(np.argmin(result.weights))  # the outlier sensor m2 gets the least weight
        1
    """
    sets = _as_focal_sets(focal_sets)
    m = check_rows(masses, "masses")
    if m.shape[-1] != len(sets):
        raise ValueError(f"masses has {m.shape[-1]} columns but {len(sets)} focal sets were given")
    if m.shape[-2] == 0:
        raise ValueError(f"masses must hold at least one source, got shape {m.shape}")
    singletons = all(len(s) == 1 for s in sets)
    if closed_form and not singletons:
        raise ValueError("closed_form=True needs every focal element to be a singleton")
    rho = check_prior(prior, m.shape[:-1])
    if singletons and closed_form is not False:
        result = bjs_dst(m, True, rho)
        assert isinstance(result, FusionResult)
        return dataclasses.replace(result, focal_sets=sets)
    batch = m.shape[:-2]
    p = None if rho is None else _prior_columns(rho)
    columns = _columns_wae(_to_columns(m), _log2_capacity(sets), p)
    wae, weights, crd, entropy = (_from_columns(x, batch) for x in columns)
    fused, out, conflicts = _general_self_combination(wae, sets, m.shape[-2])
    return FusionResult(
        fused=fused,
        weights=weights,
        credibility=crd,
        entropy=entropy,
        conflicts=conflicts,
        focal_sets=out,
        wae=wae,
        rule="bjs-dst",
    )


def check_prior(prior: npt.ArrayLike | None, batch_shape: tuple[int, ...]) -> np.ndarray | None:
    """A member prior checked and broadcast to ``batch_shape``; None for none or a constant one.

    A constant prior cancels in the normalised weights: None keeps the paper's arithmetic.
    Raises ValueError: not broadcastable, NaN/inf, negative, or all zero for some state.
    """
    if prior is None:
        return None
    rho = check_weights(prior, batch_shape, "prior")
    if rho.size == 0 or np.all(rho == rho[..., :1]):
        return None
    return rho


def bjs_dst(
    beliefs: np.ndarray, diagnostics: bool = False, prior: np.ndarray | None = None
) -> np.ndarray | FusionResult:
    """Apply ``bjs-dst`` to validated singleton beliefs ``(..., k, n)`` by the closed form.

    ``prior`` (`check_prior`): ``w_i = rho_i ACrd_i / sum_j rho_j ACrd_j``. Blocks of ``_BLOCK``
    states fit the CPU cache (about 1.5x faster, measured).
    """
    batch = beliefs.shape[:-2]
    k, n = beliefs.shape[-2:]
    flat = beliefs.reshape(-1, k, n)
    size = flat.shape[0]
    flat_prior = None if prior is None else np.broadcast_to(prior, (*batch, k)).reshape(-1, k)
    fused = np.empty((size, n))
    blocks = []  # (wae, weights, crd, entropy, conflicts) columns of each block, diagnostics only
    for start in range(0, max(size, 1), _BLOCK):
        stop = min(start + _BLOCK, size)
        rho = None if flat_prior is None else _prior_columns(flat_prior[start:stop])
        wae, weights, crd, entropy = _columns_wae(_to_columns(flat[start:stop]), None, rho)
        block, conflicts = _columns_closed_form(wae, k, diagnostics)
        fused[start:stop] = block.T
        if diagnostics:
            blocks.append((wae, weights, crd, entropy, conflicts))
    fused = fused.reshape(*batch, n)
    if not diagnostics:
        return fused
    wae, weights, crd, entropy, conflicts = (
        np.concatenate(c, axis=1).T for c in zip(*blocks, strict=True)
    )
    return FusionResult(
        fused=fused,
        weights=weights.reshape(*batch, k),
        credibility=crd.reshape(*batch, k),
        entropy=entropy.reshape(*batch, k),
        conflicts=conflicts.reshape(*batch, k - 1),
        wae=wae.reshape(*batch, n),
        rule="bjs-dst",
    )
