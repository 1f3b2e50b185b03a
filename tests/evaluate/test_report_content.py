"""What report.md says and what its figures show, on hand-made results with known numbers.

The results dicts below are written by hand in the shape ``evaluate_run`` returns; every
expected value in the assertions is worked out here from those numbers (or, for colours,
taken from matplotlib's documented tab10 palette), not read back from the code.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest
from matplotlib.colors import to_hex
from report_tables import rows_of
from sparse_files import sparse
from tiny_cli import RULES, TINY, one_line

from amuled_ma.cli import main
from amuled_ma.evaluate.report.bars import ablation_figure, bars_figure
from amuled_ma.evaluate.report.curves import curves_figure
from amuled_ma.evaluate.report.describe import settings_table
from amuled_ma.evaluate.report.plotting import compact_number, robust_ylim, variant_colors
from amuled_ma.evaluate.report.tables import (
    agents_table,
    base_differences,
    differences_table,
    same_as_base,
)
from amuled_ma.evaluate.report.trajectories import episode_figure
from amuled_ma.evaluate.report.writing import link_viewer, write_report
from amuled_ma.evaluate.results import Results
from amuled_ma.records.run_record import RunRecord
from amuled_ma.tasks.drawing import findmilk_subgoals

SHA = "0f" * 32

#: matplotlib's tab10, C0..C3 (documented default colour cycle).
TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728"]


def stat(mean: float | None, half: float = 0.0, n: int = 5) -> dict:
    return {"mean": mean, "half_width": half, "n": n, "std": 0.0,
            "ci_low": mean, "ci_high": mean}  # fmt: skip


def trajectory(cells: list[tuple[int, int]]) -> dict:
    """A FindMilk episode along ``cells`` on the paper's layout (milk at 7, 7)."""
    return {
        "obs": [[x, y, 7, 7, 0, 0, 0, 0] for x, y in cells],
        "actions": [0] * (len(cells) - 1),
        "events": {},
        "layout": {
            "crying": [[2, 2], [2, 3], [4, 4], [5, 6], [6, 7]],
            "sleeping": [[1, 1], [3, 3], [4, 0], [5, 4], [5, 5], [6, 6]],
        },
    }


def mode_entry(metrics: dict[str, float], cells=((0, 0), (1, 0))) -> dict:
    return {
        "metrics": {k: stat(v) for k, v in metrics.items()},
        "ci_over": "episodes",
        "n_seeds": 1,
        "trajectory": trajectory(list(cells)),
    }


BASE = {"steps_to_milk": 14.0, "crying_pacified": 3.8, "sleeping_woken": 2.6, "reached_milk": 1.0}
# differs from base by +57.2, +0.4, -1.6, -0.2
HUMAN = {"steps_to_milk": 71.2, "crying_pacified": 4.2, "sleeping_woken": 1.0, "reached_milk": 0.8}


def panel(**changes) -> dict:
    entry = {
        "feedback": "amuled",
        "recipe": "authors",
        "lambda_kl": 0.05,
        "iterations": 1000,
        "seed": 42,
        "agents": ["consequentialist", "deontological", "virtue", "care", "social_justice"],
        "source": "replay",
        "model": "gpt-4o-mini",
        "recording": "findmilk-gpt-4o-mini.json",
        "fusion": "bjs-dst",
        "agent_sources": {},
        "inputs": {"recording_sha256": SHA},
    }
    entry.update(changes)
    return entry


def agent_row(**counts) -> dict:
    row = dict.fromkeys(("ok", "repaired", "abstained", "timeout", "error", "replay_miss"), 0)
    row.update(counts)
    total = sum(row.values())
    failed = total - row["ok"] - row["repaired"]
    row.update(total=total, failed=failed, failure_rate=failed / total)
    return row


def results(amuled: dict[str, float] | None = None) -> dict:
    """base, finetune-amuled (greedy equal to base unless given) and finetune-human."""
    amuled = dict(BASE) if amuled is None else amuled
    return {
        "scenario": "findmilk",
        "task": "findmilk",
        "episodes": 50,
        "confidence": 0.95,
        "seed": 42,
        "variants": {
            "base": {"greedy": mode_entry(BASE), "sampled": mode_entry(BASE)},
            "finetune-amuled": {
                "greedy": mode_entry(amuled),
                "sampled": mode_entry(HUMAN),
                "panel": panel(),
                "feedback": {
                    "feedback": "amuled",
                    "mean_weight": {"care": 0.5, "virtue": 0.5},
                    "mean_conflict": 0.25,
                    "miss_rate": 0.05,
                    "unique_states": 12,
                    # care: 8 of 40 abstained (20%), 2 repaired (5%);
                    # virtue: 4 of 40 replay misses (10%)
                    "agents": {
                        "care": agent_row(ok=30, repaired=2, abstained=8),
                        "virtue": agent_row(ok=36, replay_miss=4),
                    },
                },
            },
            "finetune-human": {
                "greedy": mode_entry(HUMAN, cells=((0, 0), (1, 0), (1, 1), (2, 1), (2, 2))),
                "panel": panel(feedback="human", agents=None, source=None, inputs=None),
            },
        },
    }


CONFIG = {
    "scenario": {
        "name": "findmilk",
        "base": {"total_steps": 500_000},
        "finetune": {"recipe": "authors", "lambda_kl": 0.05, "iterations": 1000},
        "feedback": {"source": "replay", "clusters": ["care", "virtue"], "fusion": "bjs-dst"},
    },
    "seeds": [42, 43, 44],
}


# ---------------------------------------------------------------------------------------
# Tables


def test_settings_header_names_task_recipe_lambda_iterations_seeds_panel_and_recording():
    rows = rows_of(
        settings_table(Results.model_validate(results()), RunRecord.model_validate(CONFIG))
    )
    assert rows["task"] == ["`findmilk` (scenario `findmilk`)"]
    assert rows["evaluation"] == [
        "50 episodes per variant and mode, seeds from 42, 95% Student-t intervals"
    ]
    assert rows["training seeds"] == ["3: 42, 43, 44"]
    assert rows["base training"] == ["500,000 env steps per policy"]
    assert rows["fine-tune recipe"] == ["authors"]
    assert rows["lambda_KL"] == ["0.05"]
    assert rows["fine-tune iterations"] == ["1000"]
    assert rows["panel"] == [
        "consequentialist, deontological, virtue, care, social_justice; fusion `bjs-dst`"
    ]
    assert rows["beliefs from"] == ["replay of `findmilk-gpt-4o-mini.json`"]
    assert rows["recording"] == [f"`findmilk-gpt-4o-mini.json` sha256 `{SHA}`"]


def test_settings_header_lists_each_lambda_when_the_fine_tunes_differ():
    res = results()
    res["variants"]["finetune-human"]["panel"]["lambda_kl"] = 10.0
    rows = rows_of(settings_table(Results.model_validate(res), RunRecord()))
    assert rows["lambda_KL"] == ["0.05, 10 (per variant)"]
    assert rows["training seeds"] == ["1"]  # no config.json: the most seeds of a variant


def test_differences_to_base_are_mean_minus_base_mean():
    res = results(amuled=dict(BASE, crying_pacified=4.8))
    diffs = base_differences(Results.model_validate(res), "greedy")
    assert set(diffs) == {"finetune-amuled", "finetune-human"}
    assert diffs["finetune-human"]["steps_to_milk"] == pytest.approx(57.2)
    assert diffs["finetune-human"]["sleeping_woken"] == pytest.approx(-1.6)
    rows = rows_of(differences_table(Results.model_validate(res), "greedy"))
    # columns: steps_to_milk, crying_pacified, sleeping_woken, reached_milk
    assert rows["finetune-human"] == ["+57.20", "+0.40", "-1.60", "-0.20"]
    assert rows["finetune-amuled"] == ["=", "+1.00", "=", "="]
    assert "base" not in rows


def test_equals_base_sentence_only_for_a_fine_tune_equal_to_base(tmp_path):
    res = results()  # finetune-amuled's greedy metrics are base's
    res["variants"]["finetune-amuled"]["greedy"]["metrics"]["steps_to_milk"]["mean"] += 1e-12
    assert same_as_base(Results.model_validate(res)) == ["finetune-amuled"]
    text = write_report(tmp_path, Results.model_validate(res)).read_text()
    assert "finetune-amuled behaves exactly as the base policy (greedy)" in text
    assert "finetune-human behaves exactly" not in text

    res = results(amuled=dict(BASE, steps_to_milk=14.000001))  # 1e-6 apart: not equal
    assert same_as_base(Results.model_validate(res)) == []
    text = write_report(tmp_path, Results.model_validate(res)).read_text()
    assert "behaves exactly as the base policy" not in text


def test_agents_table_gives_each_agents_abstention_and_replay_miss_rates():
    rows = {
        tuple(line.strip("|").split("|")[:2]): [c.strip() for c in line.strip("|").split("|")]
        for line in agents_table(Results.model_validate(results())).splitlines()[2:]
    }
    head = agents_table(Results.model_validate(results())).splitlines()[0]
    assert head == (
        "| variant | agent | beliefs | repaired | abstained | replay miss | timeout | error "
        "| not answered |"
    )
    care = rows[(" finetune-amuled ", " care ")]
    assert care[2:] == ["40", "5.0%", "20.0%", "0.0%", "0.0%", "0.0%", "20.0%"]
    virtue = rows[(" finetune-amuled ", " virtue ")]
    assert virtue[2:] == ["40", "0.0%", "0.0%", "10.0%", "0.0%", "0.0%", "10.0%"]
    assert agents_table(Results.model_validate({"variants": {"base": {"greedy": {}}}})) == ""


# ---------------------------------------------------------------------------------------
# Figures


def test_variant_colours_are_fixed_by_the_sorted_names():
    one = variant_colors(["shaped", "base", "finetune-amuled", "finetune-human"])
    two = variant_colors(["finetune-human", "finetune-amuled", "shaped", "base", "base"])
    assert one == two
    # sorted: base, finetune-amuled, finetune-human, shaped -> tab10 C0..C3
    assert one == dict(zip(["base", "finetune-amuled", "finetune-human", "shaped"], TAB10,
                           strict=True))  # fmt: skip
    many = variant_colors([f"v{i:02d}" for i in range(14)])
    assert len(set(many.values())) == 14


def test_a_variant_has_the_same_colour_in_bars_trajectories_and_curves():
    res = results(amuled=HUMAN)
    curves = {
        name: [[{"env_steps": 100 * i, "episode/return_env": float(i)} for i in range(1, 6)]]
        for name in res["variants"]
    }
    colors = variant_colors([*res["variants"], *curves])
    bars = bars_figure(Results.model_validate(res), "greedy", colors=colors)
    names = list(res["variants"])
    bar_colour = {n: to_hex(p.get_facecolor()) for n, p in zip(names, bars.axes[0].patches,
                                                                 strict=True)}  # fmt: skip
    grid = episode_figure(Results.model_validate(res), colors=colors)
    path_colour = {
        ax.get_title().split("\n")[0]: to_hex(line.get_color())
        for ax in grid.axes
        for line in ax.get_lines()
        if line.get_gid() == "path"
    }
    lines = curves_figure(curves, ["episode/return_env"], "t", colors).axes[0].get_lines()
    curve_colour = {
        line.get_label(): to_hex(line.get_color())
        for line in lines
        if line.get_gid() == "mean-line"
    }
    expected = {"base": TAB10[0], "finetune-amuled": TAB10[1], "finetune-human": TAB10[2]}
    assert bar_colour == path_colour == curve_colour == expected


def test_robust_y_range_leaves_out_an_early_spike_and_says_so():
    # 40 points: the first 5% (2 points) are a spike of 100 and 90, the rest 1.00..1.37
    series = [100.0, 90.0] + [1.0 + 0.01 * i for i in range(38)]
    low, high, note = robust_ylim([series])
    assert 1.37 < high < 2.0 and low < 1.0 and note == "early values above the range clipped"
    # a spike in the middle is clipped too, and not called early
    middle = [1.0 + 0.01 * i for i in range(40)]
    middle[20] = 100.0
    assert robust_ylim([middle])[2] == "values above the range clipped"
    # no spike: every value in view, nothing said; a ramp within one range stays in view
    ramp = [0.8, 0.9] + [1.0 + 0.01 * i for i in range(38)]
    low, high, note = robust_ylim([ramp])
    assert low < 0.8 and high > 1.37 and note == ""

    curves = {"finetune-amuled": [[{"env_steps": 1000 * (i + 1), "feedback/kl": v}
                                   for i, v in enumerate(series)]]}  # fmt: skip
    ax = curves_figure(curves, ["feedback/kl"], "fine-tuning").axes[0]
    # the rolling mean (window 2) starts 100, 95, 45.5, then 1.0 ... 1.37
    assert 1.37 < ax.get_ylim()[1] < 2.0
    assert "clipped" in ax.get_title()


def test_compact_tick_labels():
    assert [compact_number(v) for v in (0, 950, 20_000, 12_500, 1_250_000)] == [
        "0", "950", "20k", "12.5k", "1.25M",
    ]  # fmt: skip


def test_a_zero_bar_gets_a_marker_and_every_bar_a_value_label():
    res = results(amuled=dict(HUMAN, crying_pacified=0.0))
    fig = bars_figure(Results.model_validate(res), "greedy")
    ax = next(a for a in fig.axes if a.get_title() == "crying pacified")
    markers = [line for line in ax.get_lines() if line.get_gid() == "zero-bar"]
    assert len(markers) == 1
    # variants top to bottom: base (y=2), finetune-amuled (y=1), finetune-human (y=0)
    assert list(markers[0].get_xdata()) == [0.0] and list(markers[0].get_ydata()) == [1]
    labels = [t.get_text() for t in ax.texts if t.get_gid() == "bar-label"]
    assert labels == ["3.80", "0", "4.20"]


def test_findmilk_subgoals_from_the_path():
    # (0,0) -> (1,0) -> (1,1) sleeping -> (2,1) -> (2,2) crying
    goals = findmilk_subgoals(trajectory([(0, 0), (1, 0), (1, 1), (2, 1), (2, 2)]))
    assert goals["woken"] == [(1, 1)] and goals["pacified"] == [(2, 2)]
    assert goals["reached_milk"] is False and goals["end"] == (2, 2)
    grid = episode_figure(Results.model_validate(results()))
    human = next(a for a in grid.axes if a.get_title().startswith("finetune-human"))
    assert "pacified 1/5, woken 1/6" in human.get_title()


def test_ablation_figure_sorts_the_fine_tunes_and_draws_base():
    res = {
        "scenario": "findmilk",
        "task": "findmilk",
        "variants": {
            "base": {"greedy": mode_entry(dict(BASE, crying_pacified=0.5))},
            "finetune-amuled": {"greedy": mode_entry(dict(BASE, crying_pacified=3.0))},
            "finetune-cluster-care": {"greedy": mode_entry(dict(BASE, crying_pacified=1.0))},
            "finetune-moral": {"greedy": mode_entry(dict(BASE, crying_pacified=2.0))},
        },
    }
    fig = ablation_figure(Results.model_validate(res), "clusters")
    ax = next(a for a in fig.axes if a.get_title() == "crying pacified")
    # bottom to top: smallest to largest mean
    assert [t.get_text() for t in ax.get_yticklabels()] == [
        "finetune-cluster-care", "finetune-moral", "finetune-amuled",
    ]  # fmt: skip
    base = [line for line in ax.get_lines() if line.get_gid() == "base-line"]
    assert len(base) == 1 and list(base[0].get_xdata()) == [0.5, 0.5]

    for name, lam in (("finetune-amuled", 2.5), ("finetune-cluster-care", 10.0),
                      ("finetune-moral", 0.0)):  # fmt: skip
        res["variants"][name]["panel"] = {"lambda_kl": lam}
    ax = next(
        a
        for a in ablation_figure(Results.model_validate(res), "kl").axes
        if a.get_title() == "crying pacified"
    )
    assert [t.get_text() for t in ax.get_xticklabels()] == ["0", "2.5", "10"]


# ---------------------------------------------------------------------------------------
# The viewer line


def test_report_points_at_the_viewer_and_links_it_once_written(tmp_path):
    text = write_report(tmp_path, Results.model_validate(results())).read_text()
    # no page yet: the report names the command that writes it, never "open" a missing file
    assert f"run `amuled view {tmp_path}` to write `view-episode0.html`" in text
    assert "open `view-episode0.html`" not in text
    assert "](view-episode0.html)" not in text
    (tmp_path / "view-episode0.html").write_text("<!DOCTYPE html>")
    assert link_viewer(tmp_path)
    text = (tmp_path / "report.md").read_text()
    assert "open [`view-episode0.html`](view-episode0.html)" in text
    assert text.count("view-episode0.html") == 2  # one line: the link and its label
    # a report written when the page exists links it straight away
    assert (
        "](view-episode0.html)"
        in write_report(tmp_path, Results.model_validate(results())).read_text()
    )


# ---------------------------------------------------------------------------------------
# A real tiny run


def figures_check(folder: Path) -> list[str]:
    """Every PNG of ``folder`` is referenced by its report.md, and no two are the same."""
    report = (folder / "report.md").read_text()
    pngs = sorted(p.name for p in folder.glob("*.png"))
    for name in pngs:
        assert f"]({name})" in report, f"{folder / name} is not in report.md"
    digests = {hashlib.sha256((folder / n).read_bytes()).hexdigest(): n for n in pngs}
    assert len(digests) == len(pngs), f"byte-identical figures in {folder}: {pngs}"
    referenced = re.findall(r"\]\(([^)]+\.png)\)", report)
    assert sorted(referenced) == pngs  # and every referenced figure exists
    return pngs


def test_tiny_run_and_clusters_ablation_reference_every_figure_once(tmp_path, capsys):
    from amuled_ma.commands.demo import write_demo_view

    run_dir = tmp_path / "run"
    common = ["findmilk", "--run-dir", str(run_dir), "--episodes", "2", "--jobs", "1"]
    assert main(["run", *common, *TINY, *RULES]) == 0
    pngs = figures_check(run_dir)
    assert {"metrics_greedy.png", "metrics_sampled.png", "trajectory_findmilk.png"} <= set(pngs)
    report = (run_dir / "report.md").read_text()
    rules = "| beliefs from | rules (the task's rule; the clusters' text is not read) |"
    assert rules in report and "| fine-tune iterations | 3 |" in report

    assert main(["ablate", "--what", "clusters", *common, *TINY, *RULES]) == 0
    abl = run_dir / "ablate-clusters"
    assert "ablation_clusters.png" in figures_check(abl)
    assert "| ablation | `clusters` |" in (abl / "report.md").read_text()

    # re-evaluated greedy only: the sampled figure of the earlier report is gone
    argv = ["evaluate", str(run_dir), "--episodes", "2", "--modes", "greedy", "--no-progress"]
    assert main(argv) == 0
    assert "metrics_sampled.png" not in figures_check(run_dir)

    # the demo's last step: the viewer of its AMULED fine-tune, linked from the report
    capsys.readouterr()
    page = write_demo_view(run_dir)
    assert page == run_dir / "view-episode0.html" and page.is_file()
    assert "open [`view-episode0.html`](view-episode0.html)" in (run_dir / "report.md").read_text()
    payload = re.search(r'id="amuled-data">(.*?)</script>', page.read_text(), re.S).group(1)
    assert [v["name"] for v in json.loads(payload)["variants"]] == ["finetune-amuled"]


# ---------------------------------------------------------------------------------------
# Size caps: the files the report reads are refused unread over their cap


def test_a_curve_json_over_256_mib_is_refused_by_evaluate_with_one_line(tmp_path, capsys):
    from amuled_ma.evaluate.report.curves import MAX_CURVE_BYTES

    assert MAX_CURVE_BYTES == 256 * 2**20
    run = tmp_path / "run"
    assert main(["train", "findmilk", "--run-dir", str(run), *TINY]) == 0
    path = sparse(run / "base" / "curve.json", 10 * 2**30)
    capsys.readouterr()
    argv = ["evaluate", str(run), "--episodes", "1", "--modes", "greedy", "--no-progress"]
    assert main(argv) == 1
    line = one_line(capsys.readouterr().err)
    assert line == (
        f"amuled: error: {path}: the learning curve is 10,737,418,240 bytes, more than the "
        "268,435,456 a learning curve may be (about 590 bytes an iteration); it is not read; "
        "is it the right folder? It is written by 'amuled train' and 'amuled finetune'; "
        "retrain the variant with --force, or move its folder out of the run"
    )


def test_a_report_md_over_16_mib_is_refused_unread_when_the_viewer_is_linked(tmp_path):
    from amuled_ma.errors import AmuledError
    from amuled_ma.evaluate.report.writing import MAX_REPORT_BYTES

    assert MAX_REPORT_BYTES == 16 * 2**20
    report = sparse(tmp_path / "report.md", 10 * 2**30)
    with pytest.raises(AmuledError) as info:
        link_viewer(tmp_path)
    assert str(info.value) == (
        f"{report}: the report is 10,737,418,240 bytes, more than the 16,777,216 a report may "
        "be (a report is about 10 KB); it is not read; is it the right folder? Write the "
        f"report again with 'amuled evaluate {tmp_path}'"
    )
