"""``report.md``: the run's settings, tables and figures, written into the run folder."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from amuled_ma.errors import AmuledError
from amuled_ma.evaluate.report.bars import ablation_figure, bars_figure
from amuled_ma.evaluate.report.curves import CURVE_KEYS, FT_KEYS, curves_figure, load_curves
from amuled_ma.evaluate.report.describe import (
    finetune_names,
    imported_table,
    panels_table,
    settings_table,
    unfinished_lines,
    variant_records,
)
from amuled_ma.evaluate.report.plotting import save_figure, variant_colors
from amuled_ma.evaluate.report.tables import (
    agents_table,
    budget_ablation_table,
    budget_table,
    diagnostics_table,
    differences_table,
    metrics_table,
    movement_sentence,
    paper_table,
    same_as_base,
    servers_table,
)
from amuled_ma.evaluate.report.trajectories import episode_figure
from amuled_ma.evaluate.results import RESULTS_FILES, Results
from amuled_ma.files.safe import check_write_targets, checked_read_path, write_text_atomic
from amuled_ma.records.run_record import RunRecord

#: The figures `write_report` writes; one of these it did not write this time is a
#: stale one from an earlier report and is removed, so every PNG is the report's.
FIGURE_NAMES = (
    "curves_base.png", "curves_finetune.png", "metrics_greedy.png", "metrics_sampled.png",
    "trajectory_findmilk.png", "episode_driving.png",
)  # fmt: skip
#: The viewer page ``amuled view`` writes by default (episode 0).
VIEWER_PAGE = "view-episode0.html"
#: How the report's viewer line starts (`link_viewer` finds it by this).
VIEWER_PREFIX = "**Step by step:**"
#: Largest ``report.md`` read back by `link_viewer` [bytes] (a report is about 10 KB).
MAX_REPORT_BYTES = 16 * 2**20


def viewer_line(run_dir: Path) -> str:
    """The report's pointer to ``amuled view``: a link when the page is already there."""
    run_dir = Path(run_dir)
    what = (
        "one offline HTML page replaying evaluation episode 0 of each fine-tune step by "
        "step, with every panel agent's belief, weight and reasoning"
    )
    if (run_dir / VIEWER_PAGE).is_file():
        return (
            f"{VIEWER_PREFIX} open [`{VIEWER_PAGE}`]({VIEWER_PAGE}) (or run "
            f"`amuled view {run_dir}` to write it again): {what}."
        )
    return f"{VIEWER_PREFIX} run `amuled view {run_dir}` to write `{VIEWER_PAGE}`: {what}."


def link_viewer(run_dir: Path) -> bool:
    """Rewrite ``report.md``'s viewer line (`viewer_line`); True when it had one.

    AmuledError: ``report.md`` over `MAX_REPORT_BYTES`, unsafe, unreadable, or not writable.
    """
    from amuled_ma.files.limits import read_bounded_bytes

    report = checked_read_path(run_dir, "report.md")
    if not report.is_file():
        return False
    fix = f"is it the right folder? Write the report again with 'amuled evaluate {run_dir}'"
    encoding = "utf-8"  # as write_report wrote it
    try:
        raw = read_bounded_bytes(
            report, MAX_REPORT_BYTES, "report", note="a report is about 10 KB", fix=fix
        )
        text = raw.decode(encoding)
    except OSError as err:
        raise AmuledError(f"{report}: cannot read it ({err.strerror or err}); {fix}") from None
    except UnicodeDecodeError as err:
        raise AmuledError(f"{report}: not {encoding} text ({err.reason}); {fix}") from None
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    found = False
    for i, line in enumerate(lines):
        if line.startswith(VIEWER_PREFIX):
            lines[i] = viewer_line(run_dir)
            found = True
    if found:
        write_text_atomic(report, "\n".join(lines))
    return found


def evaluation_outputs(run_dir: Path) -> list[Path]:
    """The files an evaluation and its report write or remove in ``run_dir``."""
    run_dir = Path(run_dir)
    return [
        *(run_dir / name for name in RESULTS_FILES),
        run_dir / "report.md",
        *(run_dir / name for name in FIGURE_NAMES),
        *sorted(run_dir.glob("ablation_*.png")),
    ]


def write_report(
    run_dir: Path,
    results: Results,
    *,
    title: str | None = None,
    ablation: str | None = None,
    run: RunRecord | None = None,
    records: Mapping[str, RunRecord] | None = None,
) -> Path:
    """Write ``report.md`` and its PNG figures into ``run_dir``, removing figures not drawn now.

    UnsafePathError (before any figure): one of `evaluation_outputs` is a link or not a regular
    file; FileWriteError: a file could not be written.
    """
    run_dir = Path(run_dir)
    check_write_targets(evaluation_outputs(run_dir))
    task = results.task
    ablation = ablation or (run.ablation if run is not None else None)
    described = variant_records(results, records)
    tunes = finetune_names(results, described)
    names = {folder: r.name for folder, r in (records or {}).items() if r.name}
    curves = load_curves(run_dir, names)
    colors = variant_colors([*results.variants, *curves])
    tuned = set(tunes) | {n for n, r in (records or {}).items() if r.finetuning}
    tuned |= {r.name for r in (records or {}).values() if r.finetuning and r.name}
    base_curves = {k: v for k, v in curves.items() if k not in tuned}
    ft_curves = {k: v for k, v in curves.items() if k in tuned}
    figures: list[tuple[str, str, Path | None]] = []
    if ablation:
        ablation_note = (
            "Each paper metric (greedy) and the distilled model's held-out agreement with the "
            "panel against the budget, the share of distinct states the panel was asked "
            "(log scale), one colour per selection; the grey band is the 95% CI of the "
            "fine-tune that asked every state without a model, the dashed line the base "
            "policy."
            if ablation == "budget"
            else "Each fine-tune of the ablation against AMULED on the paper's metrics that "
            "differ between the fine-tunes (greedy, then sampled; the title names those left "
            "out as equal), "
            + ("against lambda_KL." if ablation == "kl" else "sorted by the metric's mean.")
            + " The dashed line is the base policy."
        )
        heading = "the feedback budget" if ablation == "budget" else ablation
        figures.append((
            f"Ablation of {heading}",
            ablation_note,
            save_figure(ablation_figure(results, ablation, colors),
                        run_dir / f"ablation_{ablation}.png"),
        ))  # fmt: skip
    curve_note = (
        "A panel's y-range is the 2nd-98th percentile of its lines after their first 10% of "
        "points, widened to the values within that range's width of it: a far outlier (an "
        "early spike) is clipped, and the panel's title says so."
    )
    figures += [
        ("Base training curves", curve_note,
         save_figure(curves_figure(base_curves, CURVE_KEYS.get(task, ["episode/return_env"]),
                                   "base training", colors), run_dir / "curves_base.png")),
        ("Fine-tuning curves", curve_note,
         save_figure(curves_figure(ft_curves, FT_KEYS + CURVE_KEYS.get(task, [])[1:],
                                   "fine-tuning", colors), run_dir / "curves_finetune.png")),
    ]  # fmt: skip
    for mode in ("greedy", "sampled"):
        figures.append((
            f"Metrics, {mode} policy",
            "Mean and 95% CI per variant; a thick tick at 0 marks a mean of 0.",
            save_figure(bars_figure(results, mode, colors=colors), run_dir / f"metrics_{mode}.png"),
        ))  # fmt: skip
    episode_figures = {
        "findmilk": ("A FindMilk trajectory per variant", "trajectory_findmilk"),
        "driving": ("A Driving episode per variant", "episode_driving"),
    }
    if task in episode_figures:
        heading, stem = episode_figures[task]
        figures.append((
            heading,
            "The first greedy evaluation episode of each variant.",
            save_figure(episode_figure(results, colors=colors), run_dir / f"{stem}.png"),
        ))  # fmt: skip
    written = {path.name for _, _, path in figures if path is not None}
    for stale in evaluation_outputs(run_dir):  # a figure of an earlier report not drawn now
        if stale.suffix == ".png" and stale.name not in written and stale.is_file():
            stale.unlink()
    lines = [
        f"# {title or 'Run report: ' + str(results.scenario)}",
        "",
        "## Settings",
        "",
        settings_table(results, run, records),
    ]
    imported = imported_table(described)
    if imported:
        lines += [
            "Imported policies, not trained here (`amuled import authors`): the authors' "
            "file each was converted from and its checkpoint iteration.",
            "",
            imported,
        ]
    amuled = [n for n in results.variants if n.split(".seed", 1)[0] == "finetune-amuled"]
    moved = [movement_sentence(results, amuled[0], m) for m in ("sampled", "greedy") if amuled]
    sentences = [s for s in moved if s]
    paper = paper_table(
        results, {n: r.recipe for n, r in described.items() if r is not None and r.recipe}
    )
    if sentences or paper:
        lines += ["## What AMULED did, beside the paper", ""]
        lines += [*(f"- {s}" for s in sentences), ""] if sentences else []
        lines += [paper] if paper else []
    unfinished = unfinished_lines(described)
    if unfinished:
        lines += [*unfinished, ""]
    if tunes:
        lines += [viewer_line(run_dir), ""]
    lines += [
        f"Figures are mean ± half-width of the {100 * results.confidence:g}% "
        "Student-t confidence interval. A variant trained with one seed has its interval over "
        "the evaluation episodes; one trained with several (column *seeds*) has the mean of "
        "its per-seed means and the interval over the seeds, so it covers the spread of "
        "training runs.",
        "",
    ]
    for mode in ("greedy", "sampled"):
        table = metrics_table(results, mode)
        if not table:
            continue
        lines += [f"## Metrics, {mode} policy", "", table]
        diffs = differences_table(results, mode)
        if diffs:
            lines += [
                f"Difference to the base policy ({mode}): each variant's mean minus base's "
                "mean; `=` is equal within 1e-9.",
                "",
                diffs,
            ]
        same = same_as_base(results, mode, tunes) if mode == "greedy" else []
        stopped = [n for n in same if (r := described.get(n)) is not None and r.unfinished]
        same = [n for n in same if n not in stopped]
        for name in stopped:
            record = described[name]
            assert record is not None
            lines += [
                f"- **{name} scores exactly as the base policy (greedy): its training "
                f"{record.state} at iteration {record.iterations_done} of "
                f"{record.iterations_planned}.**",
                "",
            ]
        if same:
            lines += [f"- **{name} behaves exactly as the base policy (greedy).**" for name in same]
            lines += [
                "",
                f"Every greedy metric of {'this fine-tune' if len(same) == 1 else 'these'} "
                "equals base's within 1e-9: the fine-tune did not change what the greedy "
                "policy achieves (a strong KL anchor, or too few iterations, keeps its most "
                "probable actions; the sampled policy may still differ).",
                "",
            ]
    sections = [
        (
            "Feedback of each fine-tune",
            "What each fine-tuned variant was trained on (its folder's `config.json`): the "
            "recipe of the KL anchor, lambda_KL, the panel's agents and where their beliefs "
            "came from.",
            panels_table(described),
        ),
        (
            "Fused-belief diagnostics",
            "Mean weight of each cluster in the fusion and mean Dempster conflict over the "
            "fine-tuning steps (which cluster drove the agent), and the replay miss rate.",
            diagnostics_table(results, len(tunes)),
        ),
        (
            "What the figures mean",
            "One sentence per figure that changes how the result reads (the thresholds are "
            "in amuled_ma/deliberation/summaries.py, `readings`).",
            "".join(f"{line}\n" for line in readings_lines(results)),
        ),
        (
            "Answers of each panel agent",
            "Per fine-tune and agent, over the rewarded fine-tuning steps: how many beliefs "
            "it gave and the share repaired (answered after the parser repaired the reply), "
            "abstained, missed by the replay, timed out or failed. *Not answered* counts "
            "every status but ok and repaired: there the agent abstained (weight 0) and the "
            "fusion went on without it.",
            agents_table(results),
        ),
        (
            "Feedback budget",
            "Fine-tunes whose panel was asked on a budget (`[feedback.distill]`, "
            "docs/distill.md): of the distinct states visited, how many the panel was asked "
            "(the budget caps them), how many the distilled model answered instead, the "
            "misses and abstentions of asked states it answered, the requests handed to the "
            "panel's source and how many of them were sent to the LLMs (the others were in "
            "the belief store), the model's refits, and its agreement with the panel on the "
            "held-out asked states (mean total-variation distance: 0 agrees, 1 disagrees "
            "entirely) of the fused belief and of each member.",
            budget_table(results),
        ),
        (
            "Metrics against the budget",
            "The paper's metrics (greedy, mean ± half-width of the 95% CI) of each distilled "
            "fine-tune by selection and budget, and of the fine-tune that asked the panel about "
            "every state.",
            budget_ablation_table(results) if ablation == "budget" else "",
        ),
        (
            "LLM servers",
            "Per fine-tune and LLM server: requests sent (every attempt, retries and probes "
            "included), answered, failed (by kind), retried on another server of the pool "
            "after failing there, times taken out of the pool and put back, and the latency "
            "of the answered requests (the 95th percentile over seed replicas is the largest "
            "replica's). Each request went to the least-busy live server "
            "(amuled-ma's docs/ollama.md, section 'A pool of servers').",
            servers_table(results),
        ),
    ]
    for heading, intro, body in sections:
        if body:
            lines += [f"## {heading}", "", intro, "", body]
    lines += ["## Figures", ""]
    for caption, note, path in figures:
        if path is not None:
            lines += [f"### {caption}", "", note, "", f"![{caption}]({path.name})", ""]
    return write_text_atomic(run_dir / "report.md", "\n".join(lines))


def readings_lines(results: Results) -> list[str]:
    """Markdown bullets ``- **variant**: sentence``, one per feedback reading (`readings`)."""
    from amuled_ma.deliberation.summaries import readings

    return [
        f"- **{name}**: {sentence}"
        for name, variant in results.variants.items()
        if variant.feedback is not None
        for sentence in readings(variant.feedback.model_dump())
    ]
