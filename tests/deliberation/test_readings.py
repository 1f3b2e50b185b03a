"""A feedback summary's one-sentence readings: each appears exactly when its condition holds."""

from __future__ import annotations

import math

from amuled_ma.deliberation.summaries import readings, summary_lines


def _flat_share(p: list[float]) -> float:
    """Entropy of ``p`` over log2 of its length, computed here (not by the code under test)."""
    return -sum(x * math.log2(x) for x in p) / math.log2(len(p))


def test_repaired_majority_sentence_only_past_half() -> None:
    """3 repaired of 5 answers (60%) reads as a format problem; 2 of 4 (50%) does not."""
    summary = {
        "agents": {
            "care": {"ok": 2, "repaired": 3, "error": 7, "total": 12},
            "virtue": {"ok": 2, "repaired": 2, "total": 4},
        }
    }
    lines = readings(summary)
    assert len(lines) == 1
    assert lines[0].startswith("care: 60% of answers needed a repair")


def test_tv_readings_by_threshold() -> None:
    """0.49 places 49% of the mass differently and reads as far; 0.05 close; 0.2 rough."""
    far = readings({"distill": {"holdout_tv_fused": 0.49}})
    assert far == [
        "held-out TV 0.49: on states it was not fit to, the distilled model places 49% of the "
        "probability mass differently from the panel; far from the panel: its most likely "
        "action can differ from the panel's"
    ]
    assert readings({"distill": {"holdout_tv_fused": 0.05}})[0].endswith("close to the panel")
    assert readings({"distill": {"holdout_tv_fused": 0.2}})[0].endswith(
        "a rough stand-in for the panel"
    )
    assert readings({"distill": {"holdout_tv": None}}) == []


def test_distilled_share_sentence() -> None:
    """37 of 100 beliefs from the distilled model: 37%; none from it: no sentence."""
    summary = {
        "distill": {"budget": 20},
        "statuses": {"ok": 63, "distilled": 30, "distilled_miss": 7},
    }
    assert readings(summary) == [
        "37% of the beliefs came from the distilled model, not the panel: on those steps the "
        "reward is the distilled model's guess (its agreement is the held-out TV)"
    ]
    assert readings({"distill": {"budget": 20}, "statuses": {"ok": 100}}) == []


def test_flat_agent_with_largest_weight() -> None:
    """A near-flat agent (0.26/0.24/0.24/0.26) with the top weight (0.29) is flagged."""
    flat = _flat_share([0.26, 0.24, 0.24, 0.26])
    assert abs(flat - 0.9994) < 1e-4
    weights = {"rules": 0.29, "care": 0.24, "virtue": 0.23, "duty": 0.24}
    lines = readings({"mean_weight": weights, "mean_entropy_share": {"rules": flat, "care": 0.5}})
    assert lines == [
        "rules's beliefs are nearly flat (entropy 1.00 of max) yet it carries the largest "
        "weight (0.29): Xiao's weighting rewards information volume (Deng entropy), so a flat "
        "agent gains weight; consider dropping it or giving it a prior weight"
    ]
    peaked = _flat_share([0.7, 0.1, 0.1, 0.1])  # 0.678 of max
    assert readings({"mean_weight": weights, "mean_entropy_share": {"rules": peaked}}) == []
    # flat but not the heaviest: no sentence
    assert readings({"mean_weight": weights, "mean_entropy_share": {"care": flat}}) == []


def test_summary_lines_carry_the_readings() -> None:
    """The terminal summary prints each reading on its own line."""
    summary = {"statuses": {"ok": 1, "repaired": 3}, "agents": {"care": {"ok": 1, "repaired": 3}}}
    lines = summary_lines(summary)
    assert "  reading: care: 75% of answers needed a repair" in "\n".join(lines)


def test_report_readings_per_variant() -> None:
    """The report's bullets name the variant; a variant whose figures call for none has none."""
    from amuled_ma.evaluate.report.writing import readings_lines
    from amuled_ma.evaluate.results import Results

    results = Results.model_validate(
        {
            "variants": {
                "base": {},
                "finetune-amuled": {"feedback": {"distill": {"holdout_tv_fused": 0.71}}},
                "finetune-plain": {"feedback": {"agents": {"care": {"ok": 9, "repaired": 1}}}},
            }
        }
    )
    lines = readings_lines(results)
    assert lines == [
        "- **finetune-amuled**: held-out TV 0.71: on states it was not fit to, the distilled "
        "model places 71% of the probability mass differently from the panel; far from the "
        "panel: its most likely action can differ from the panel's"
    ]
