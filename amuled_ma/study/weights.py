"""Panel weights learned from people: the member prior whose fusion best predicts their choices.

The choice model and the fit: docs/study.md, "Panel weights learned from people".
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from amuled_ma.beliefs.types import FUSED_STATUSES
from amuled_ma.files.safe import check_write_target, write_text_atomic
from amuled_ma.fusion import fuse
from amuled_ma.scenario.panel_weights import HeldOut, PanelWeights, WeightsProvenance
from amuled_ma.study.analysis import attentive, load, pair_answers
from amuled_ma.study.answers import Answer
from amuled_ma.study.model import STUDY_FILE, Study, StudyError

#: The choice model's floor ``eps``: the least probability of either option.
FLOOR = 1e-3
#: The ridge ``RIDGE/2 sum (theta_i - mean theta)^2`` on the softmax logits.
RIDGE = 0.01
#: Bounds of the fitted logits and of ``log tau``.
LOGIT_BOUND = 20.0
LOG_TEMPERATURE_BOUNDS = (math.log(1e-3), math.log(1e3))
#: The file ``amuled study fit-weights`` writes in a study folder.
WEIGHTS_FILE = Path("analysis") / "weights.json"
_TINY = 1e-300


@dataclass(frozen=True)
class ChoiceData:
    """A study's ``bjs-dst`` pair items (``N``) and the answers (``M``) about them, as arrays.

    ``base`` ``(N, K)``: the fusion's weights without a prior (0: no answer); ``mass_a``/``mass_b``
    each member's belief in A's/B's action; ``size`` ``(N,)`` the members who answered.
    """

    members: tuple[str, ...]
    items: tuple[str, ...]
    base: np.ndarray
    mass_a: np.ndarray
    mass_b: np.ndarray
    size: np.ndarray
    participants: tuple[str, ...]
    answer_participant: np.ndarray
    answer_item: np.ndarray
    answer_a: np.ndarray

    def counts(self, per_participant: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per item, the answers for A and for B (``p`` weighted ``per_participant[p]``)."""
        weight = np.ones(len(self.answer_item))
        if per_participant is not None:
            weight = np.asarray(per_participant, dtype=np.float64)[self.answer_participant]
        n = len(self.items)
        n_a = np.bincount(self.answer_item, weight * self.answer_a, minlength=n)
        n_b = np.bincount(self.answer_item, weight * ~self.answer_a, minlength=n)
        return n_a, n_b


def choice_data(
    study: Study, answers: Sequence[Answer], *, keep_inattentive: bool = False
) -> ChoiceData:
    """The `ChoiceData` of a study; StudyError: no ``bjs-dst`` item, or no kept answer to one."""
    items = [
        i
        for i in study.items
        if i.kind == "pair" and i.panel is not None and i.panel.rule == "bjs-dst"
    ]
    if not items:
        raise StudyError(
            "no pair item of the study carries the beliefs of a panel fused with bjs-dst; "
            "build it from a run with an AMULED fine-tune and its belief store "
            "('amuled study build RUN --variants amuled,...')"
        )
    members: list[str] = []
    for item in items:
        assert item.panel is not None
        members += [a for a in item.panel.agents if a not in members]
    column = {m: c for c, m in enumerate(members)}
    rows, base, mass_a, mass_b, size = [], [], [], [], []
    for item in items:
        panel = item.panel
        assert panel is not None
        answered = [j for j, s in enumerate(panel.statuses) if s in FUSED_STATUSES]
        if not answered:
            continue  # nobody answered: the uniform fallback, the same for every prior
        beliefs = np.asarray(panel.beliefs, dtype=np.float64)[answered]
        # the study file rounds beliefs (study.build): a row sums to 1 only within rounding
        beliefs /= beliefs.sum(axis=1, keepdims=True)
        diag = fuse(beliefs, "bjs-dst", return_diagnostics=True)
        a, b = (o.action for o in item.options)
        w0, ma, mb = np.zeros(len(members)), np.zeros(len(members)), np.zeros(len(members))
        for row, (j, weight) in enumerate(zip(answered, np.asarray(diag.weights), strict=True)):
            c = column[panel.agents[j]]
            w0[c], ma[c], mb[c] = weight, beliefs[row, a], beliefs[row, b]
        rows.append(item.id)
        base.append(w0)
        mass_a.append(ma)
        mass_b.append(mb)
        size.append(len(answered))
    index = {item_id: n for n, item_id in enumerate(rows)}
    kept = attentive(answers, keep_inattentive=keep_inattentive)
    used = [(a, i) for a, i in pair_answers(study, answers) if a.participant in kept]
    used = [(a, i) for a, i in used if i.id in index]
    if not used:
        raise StudyError(
            f"no {'' if keep_inattentive else 'attentive '}participant answered a pair with "
            "the panel's beliefs yet; serve the study ('amuled study serve STUDY') first"
        )
    people = sorted({a.participant for a, _ in used})
    person = {p: n for n, p in enumerate(people)}
    return ChoiceData(
        members=tuple(members),
        items=tuple(rows),
        base=np.array(base),
        mass_a=np.array(mass_a),
        mass_b=np.array(mass_b),
        size=np.array(size, dtype=np.float64),
        participants=tuple(people),
        answer_participant=np.array([person[a.participant] for a, _ in used], dtype=np.int64),
        answer_item=np.array([index[i.id] for _, i in used], dtype=np.int64),
        answer_a=np.array([a.choice == "A" for a, _ in used], dtype=bool),
    )


def _softmax(theta: np.ndarray) -> np.ndarray:
    e = np.exp(theta - theta.max())
    return e / e.sum()


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # stable for any z


def choice_probability(data: ChoiceData, prior: np.ndarray, temperature: float) -> np.ndarray:
    """``P(A)`` of every item under a member prior (any scale) and a temperature ``tau > 0``."""
    z = temperature * _log_odds(data, np.asarray(prior, dtype=np.float64))[0]
    return FLOOR + (1.0 - 2.0 * FLOOR) * _sigmoid(z)  # eps + (1-2eps) f_a^tau/(f_a^tau+f_b^tau)


def _log_odds(data: ChoiceData, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``log f_a - log f_b`` per item, and the two weighted sums it is made of."""
    # bjs-dst's closed form: f_a / f_b = (sum_i rho_i w0_i m_i(a) / sum_i rho_i w0_i m_i(b))^k
    v = data.base * rho
    s_a = (v * data.mass_a).sum(axis=1) + _TINY
    s_b = (v * data.mass_b).sum(axis=1) + _TINY
    return data.size * (np.log(s_a) - np.log(s_b)), s_a, s_b


def _objective(
    free: np.ndarray,
    full: np.ndarray,
    mask: np.ndarray,
    data: ChoiceData,
    n_a: np.ndarray,
    n_b: np.ndarray,
) -> tuple[float, np.ndarray]:
    """Negative penalised log-likelihood and its gradient in the ``mask``-ed parameters of ``full``.

    The parameters are ``x = (theta_1..theta_K, log tau)``; those not in ``mask`` keep their values.
    """
    x = full.copy()
    x[mask] = free
    k = len(data.members)
    theta, eta = x[:k], x[k]
    rho = _softmax(theta)
    tau = math.exp(eta)
    odds, s_a, s_b = _log_odds(data, rho)
    z = tau * odds
    q = _sigmoid(z)
    p_a = FLOOR + (1.0 - 2.0 * FLOOR) * q
    p_b = FLOOR + (1.0 - 2.0 * FLOOR) * _sigmoid(-z)
    loglik = float(n_a @ np.log(p_a) + n_b @ np.log(p_b))
    dz = (n_a / p_a - n_b / p_b) * (1.0 - 2.0 * FLOOR) * q * (1.0 - q)  # dLL/dz
    # dz/drho_j = tau k (w0_j m_j(a) / s_a - w0_j m_j(b) / s_b); softmax's Jacobian after
    g = data.size[:, None] * data.base * (data.mass_a / s_a[:, None] - data.mass_b / s_b[:, None])
    d_rho = tau * (dz @ g)
    grad = np.empty(k + 1)
    grad[:k] = -rho * (d_rho - d_rho @ rho)
    grad[k] = -float(dz @ z)
    value = -loglik
    if mask[:k].any():
        centred = theta - theta.mean()
        value += 0.5 * RIDGE * float(centred @ centred)
        grad[:k] += RIDGE * centred
    return value, grad[mask]


@dataclass(frozen=True)
class Fit:
    """One maximum-likelihood fit: the prior (sums to 1), ``tau``, all parameters ``x``."""

    prior: np.ndarray
    temperature: float
    x: np.ndarray


def fit(
    data: ChoiceData,
    n_a: np.ndarray,
    n_b: np.ndarray,
    *,
    learn: bool = True,
    temperature: float | None = None,
    start: np.ndarray | None = None,
) -> Fit:
    """Fit the member prior (``learn``; else uniform) and ``tau`` (if None) by maximum likelihood.

    ``n_a``/``n_b`` are the (weighted) answers per item; ``start`` a previous fit's ``x``.
    """
    from scipy.optimize import minimize

    k = len(data.members)
    x = np.zeros(k + 1) if start is None else np.array(start, dtype=np.float64)
    mask = np.ones(k + 1, dtype=bool)
    if not learn:
        x[:k], mask[:k] = 0.0, False
    if temperature is not None:
        x[k], mask[k] = math.log(temperature), False
    if mask.any():
        # BFGS (SciPy's, in Python): L-BFGS-B's compiled step calls a multi-threaded BLAS
        # that made every fit of these few parameters 5x slower on a busy machine (measured)
        result = minimize(
            _objective, x[mask], args=(x, mask, data, n_a, n_b), jac=True, method="BFGS",
            options={"maxiter": 500},
        )  # fmt: skip
        x[mask] = result.x
    x[:k] = np.clip(x[:k], -LOGIT_BOUND, LOGIT_BOUND)
    x[k] = np.clip(x[k], *LOG_TEMPERATURE_BOUNDS)
    return Fit(_softmax(x[:k]), math.exp(x[k]), x)


@dataclass(frozen=True)
class WeightsFit:
    """What `fit_study` found: both fits, 95% bootstrap intervals, the held-out comparison."""

    data: ChoiceData
    learned: Fit
    low: np.ndarray
    high: np.ndarray
    temperature_interval: tuple[float, float]
    held_out: HeldOut
    draws: np.ndarray


def fit_study(
    data: ChoiceData,
    *,
    bootstrap: int = 200,
    folds: int = 5,
    seed: int = 0,
    temperature: float | None = None,
    progress: bool = False,
) -> WeightsFit:
    """The weights, bootstrap intervals and held-out comparison; StudyError: bad ``folds``."""
    people = len(data.participants)
    if not 2 <= folds <= people:
        raise StudyError(
            f"--folds {folds}: the held-out likelihood needs 2 to {people} folds, one "
            f"participant at least in each ({people} participants answered); give --folds "
            f"{max(2, min(5, people))}" + ("" if people >= 2 else " after more participants")
        )
    from tqdm.auto import tqdm

    rng = np.random.default_rng(seed)
    n_a, n_b = data.counts()
    learned = fit(data, n_a, n_b, temperature=temperature)
    bar = tqdm(total=bootstrap + folds, desc="fit-weights", unit="fit", disable=not progress)
    with bar:
        # held out: each fold scored by the models fitted on the others
        order = rng.permutation(people)
        held_fixed = np.zeros(people)
        held_learned = np.zeros(people)
        for fold in np.array_split(order, folds):
            train = np.ones(people)
            train[fold] = 0.0
            ta, tb = data.counts(train)
            on_learned = fit(data, ta, tb, temperature=temperature, start=learned.x)
            on_fixed = fit(data, ta, tb, learn=False, temperature=temperature, start=learned.x)
            test = np.isin(data.answer_participant, fold)
            for model, out in ((on_learned, held_learned), (on_fixed, held_fixed)):
                p = choice_probability(data, model.prior, model.temperature)[data.answer_item]
                scores = np.where(data.answer_a, np.log(p), np.log1p(-p))
                out += np.bincount(data.answer_participant[test], scores[test], minlength=people)
            bar.update()
        # intervals: participants resampled with replacement, refitted
        draws, temperatures = [], []
        for _ in range(bootstrap):
            chosen = np.bincount(rng.integers(people, size=people), minlength=people)
            refit = fit(data, *data.counts(chosen), temperature=temperature, start=learned.x)
            draws.append(refit.prior)
            temperatures.append(refit.temperature)
            bar.update()
    diff = held_learned - held_fixed
    resampled = [diff[rng.integers(people, size=people)].sum() for _ in range(bootstrap)]
    d_low, d_high = np.percentile(resampled, [2.5, 97.5])
    low, high = np.percentile(draws, [2.5, 97.5], axis=0)
    t_low, t_high = np.percentile(temperatures, [2.5, 97.5])
    answers = len(data.answer_item)
    held_out = HeldOut(
        folds=folds,
        answers=answers,
        fixed=float(held_fixed.sum()),
        learned=float(held_learned.sum()),
        fixed_per_answer=float(held_fixed.sum() / answers),
        learned_per_answer=float(held_learned.sum() / answers),
        difference_low=float(d_low),
        difference_high=float(d_high),
    )
    return WeightsFit(
        data=data,
        learned=learned,
        low=low,
        high=high,
        temperature_interval=(float(t_low), float(t_high)),
        held_out=held_out,
        draws=np.array(draws),
    )


def answers_sha256(data: ChoiceData) -> str:
    """SHA-256 of the answers fitted: ``participant,item,choice`` lines, sorted."""
    lines = sorted(
        f"{data.participants[p]},{data.items[i]},{'A' if a else 'B'}"
        for p, i, a in zip(data.answer_participant, data.answer_item, data.answer_a, strict=True)
    )
    return hashlib.sha256("\n".join(lines).encode("utf-8")).hexdigest()


def fit_weights(
    folder: Path,
    *,
    bootstrap: int = 200,
    folds: int = 5,
    seed: int = 0,
    keep_inattentive: bool = False,
    temperature: float | None = None,
    out: Path | None = None,
    progress: bool = False,
) -> tuple[PanelWeights, Path]:
    """``amuled study fit-weights``: fit a study's panel weights, write ``out`` (or `WEIGHTS_FILE`).

    Before any fit: StudyError as `choice_data` and `fit_study`; UnsafePathError for ``out``.
    """
    from amuled_ma.files.hashing import sha256_file

    path = Path(out) if out is not None else Path(folder) / WEIGHTS_FILE
    if path.parent.is_dir():
        check_write_target(path)
    study, answers = load(folder)
    data = choice_data(study, answers, keep_inattentive=keep_inattentive)
    result = fit_study(
        data,
        bootstrap=bootstrap,
        folds=folds,
        seed=seed,
        temperature=temperature,
        progress=progress,
    )

    def r(values: np.ndarray | tuple[float, ...] | float) -> list[float]:
        return [round(float(v), 6) for v in np.atleast_1d(values)]

    weights = PanelWeights(
        members=list(data.members),
        weights=r(result.learned.prior),
        low=r(result.low),
        high=r(result.high),
        temperature=r(result.learned.temperature)[0],
        temperature_interval=tuple(r(result.temperature_interval)),
        participants=len(data.participants),
        answers=len(data.answer_item),
        items=len(data.items),
        held_out=result.held_out,
        provenance=WeightsProvenance(
            study=str(folder),
            study_sha256=sha256_file(Path(folder) / STUDY_FILE),
            answers_sha256=answers_sha256(data),
            seed=seed,
            bootstrap=bootstrap,
            keep_inattentive=keep_inattentive,
            fixed_temperature=temperature,
        ),
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(weights.model_dump(mode="json"), indent=2, sort_keys=True)
    write_text_atomic(path, text + "\n")
    return weights, path


def summary_lines(weights: PanelWeights) -> list[str]:
    """What ``amuled study fit-weights`` prints: the weights, the temperature, held out."""
    rows = [f"  {'member':<20} {'weight':>7}  95% interval"]
    low = weights.low or [math.nan] * len(weights.members)
    high = weights.high or [math.nan] * len(weights.members)
    for name, value, lo, hi in zip(weights.members, weights.weights, low, high, strict=True):
        rows.append(f"  {name:<20} {value:7.3f}  [{lo:.3f}, {hi:.3f}]")
    fixed = weights.provenance is not None and weights.provenance.fixed_temperature is not None
    if fixed:
        rows.append(f"  choice temperature {weights.temperature:.3f} (fixed)")
    elif weights.temperature is not None and weights.temperature_interval is not None:
        t_low, t_high = weights.temperature_interval
        rows.append(f"  choice temperature {weights.temperature:.3f} [{t_low:.3f}, {t_high:.3f}]")
    h = weights.held_out
    if h is not None:
        rows.append(
            f"  held-out log-likelihood per answer ({h.folds} folds, {h.answers} answers of "
            f"{weights.participants} participants): fixed {h.fixed_per_answer:.4f}, learned "
            f"{h.learned_per_answer:.4f}; learned - fixed {h.learned - h.fixed:+.1f} "
            f"[{h.difference_low:+.1f}, {h.difference_high:+.1f}]"
        )
    return rows
