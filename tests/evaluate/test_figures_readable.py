"""Figures people can read: each one rendered and looked at in numbers.

Every figure is written to a PNG here and read back: each panel must hold ink (pixels
that are not white) and several colours. The seeds' spread must not fill a panel, an
ablation shows the metrics that differ, babies reached are solid markers in the outcome
colours, the viewer's page carries the figures' colour table, and counts print as integers.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_hex

from amuled_ma.evaluate.explain import table
from amuled_ma.evaluate.numbers import format_count, format_number
from amuled_ma.evaluate.report.bars import ablation_figure, bars_figure
from amuled_ma.evaluate.report.curves import curves_figure
from amuled_ma.evaluate.report.plotting import save_figure
from amuled_ma.evaluate.report.trajectories import episode_figure
from amuled_ma.evaluate.results import Results
from amuled_ma.evaluate.viewer import ASSETS, render_html
from amuled_ma.tasks.colors import COLORS, css_variables

LAYOUT = {
    "crying": [[2, 2], [2, 3], [4, 4], [5, 6], [6, 7]],
    "sleeping": [[1, 1], [3, 3], [4, 0], [5, 4], [5, 5], [6, 6]],
}


def stat(mean: float, half: float = 0.0) -> dict:
    return {"mean": mean, "half_width": half, "n": 20, "std": 0.0,
            "ci_low": mean - half, "ci_high": mean + half}  # fmt: skip


def findmilk_path(cells: list[tuple[int, int]]) -> dict:
    return {
        "obs": [[x, y, 7, 7, 0, 0, 0, 0] for x, y in cells],
        "actions": [0] * (len(cells) - 1),
        "events": {},
        "layout": LAYOUT,
    }


# (0,0) -> (1,1) sleeping: woken -> (2,1) -> (2,2) crying: pacified -> (2,3) crying: pacified
PATH = [(0, 0), (1, 0), (1, 1), (2, 1), (2, 2), (2, 3)]


def entry(metrics: dict[str, float], cells=PATH) -> dict:
    return {"metrics": {k: stat(v, 0.3) for k, v in metrics.items()}, "ci_over": "episodes",
            "n_seeds": 2, "trajectory": findmilk_path(list(cells))}  # fmt: skip


def panels_ink(path: Path, fig_axes: list, fig_size: tuple[float, float]) -> list[dict]:
    """Per panel of a saved PNG: non-white pixels and distinct colours inside its box."""
    from PIL import Image

    image = np.asarray(Image.open(path).convert("RGB"))
    height, width = image.shape[:2]
    out = []
    for ax in fig_axes:
        box = ax.get_position()
        x0, x1 = int(box.x0 * width), int(box.x1 * width)
        y0, y1 = int((1 - box.y1) * height), int((1 - box.y0) * height)
        crop = image[y0:y1, x0:x1].reshape(-1, 3)
        ink = int((crop.min(axis=1) < 245).sum())
        out.append({"ink": ink, "colours": len({tuple(c) for c in crop[::3]}), "px": len(crop)})
    return out


def assert_readable(fig, path: Path, min_colours: int = 4) -> list[dict]:
    axes = [ax for ax in fig.axes if ax.axison]
    save_figure(fig, path)
    stats = panels_ink(path, axes, tuple(fig.get_size_inches()))
    assert axes, "a figure without a panel"
    for ax, s in zip(axes, stats, strict=True):
        assert s["ink"] > 0.01 * s["px"], f"panel {ax.get_title()!r} of {path.name} is empty"
        assert s["colours"] >= min_colours, f"panel {ax.get_title()!r} has {s['colours']} colours"
    return stats


# ---------------------------------------------------------------------------------------
# Learning curves and the seeds


def seed_curves(n_seeds: int, n: int = 40) -> dict:
    """Two variants, ``n_seeds`` replicas each: far apart seeds (a t-band of 2 would be huge)."""
    rng = np.random.default_rng(0)
    curves = {}
    for k, name in enumerate(("base", "shaped")):
        curves[name] = [
            [{"env_steps": 1000 * (i + 1), "episode/return_env": 5.0 * k + s + 0.05 * i
              + float(rng.normal(0, 0.3))} for i in range(n)]
            for s in range(n_seeds)
        ]  # fmt: skip
    return curves


@pytest.mark.parametrize("seeds", [2, 3, 5])
def test_two_to_five_seeds_are_lines_and_no_band_fills_the_panel(seeds, tmp_path):
    curves = seed_curves(seeds)
    fig = curves_figure(curves, ["episode/return_env"], "t")
    ax = fig.axes[0]
    seed_lines = [line for line in ax.get_lines() if line.get_gid() == "seed-line"]
    means = [line for line in ax.get_lines() if line.get_gid() == "mean-line"]
    assert len(seed_lines) == 2 * seeds and len(means) == 2
    assert not ax.collections, "no band with 2-5 seeds: each seed is drawn"
    # every seed line is in view: the y-range covers the seeds, not a t-band of 1 dof
    low, high = ax.get_ylim()
    values = np.concatenate([line.get_ydata() for line in seed_lines[:]])
    values = values[np.isfinite(values)]
    span = values.max() - values.min()
    assert high - low < 1.5 * span and low <= np.percentile(values, 5)
    assert "faint: each seed" in fig._suptitle.get_text()
    assert_readable(fig, tmp_path / "curves.png")


def test_many_seeds_get_a_light_band_cut_to_the_panel(tmp_path):
    fig = curves_figure(seed_curves(8), ["episode/return_env"], "t")
    ax = fig.axes[0]
    bands = [c for c in ax.collections if c.get_gid() == "seed-band"]
    assert len(bands) == 2 and all(b.get_alpha() <= 0.2 for b in bands)
    low, high = ax.get_ylim()
    for band in bands:
        ys = np.concatenate([p.vertices[:, 1] for p in band.get_paths()])
        assert ys.min() >= low - 1e-9 and ys.max() <= high + 1e-9
    assert not [line for line in ax.get_lines() if line.get_gid() == "seed-line"]
    assert "95% interval over seeds" in fig._suptitle.get_text()
    assert_readable(fig, tmp_path / "curves8.png")


def test_one_seed_shows_its_raw_values_faint():
    fig = curves_figure(seed_curves(1), ["episode/return_env"], "t")
    raw = [line for line in fig.axes[0].get_lines() if line.get_gid() == "raw-line"]
    assert len(raw) == 2 and all(line.get_alpha() < 0.5 for line in raw)


def two_seed_bars(n_seeds: int) -> dict:
    """Two variants with ``n_seeds`` replicas 1.0 apart; the 95% CI over 2 seeds is huge."""
    variants = {}
    for k, name in enumerate(("base", "finetune-amuled")):
        seeds = [4.0 + k + s for s in range(n_seeds)]
        mean = float(np.mean(seeds))
        half = 12.706 * float(np.std(seeds, ddof=1)) / np.sqrt(n_seeds)  # t(0.975, 1 dof)
        variants[name] = {"greedy": {
            "metrics": {"crying_pacified": stat(mean, half)}, "ci_over": "seeds",
            "n_seeds": n_seeds,
            "replicas": {f"seed{42 + s}": {"crying_pacified": stat(v)}
                         for s, v in enumerate(seeds)},
        }}  # fmt: skip
    return {"scenario": "findmilk", "task": "findmilk", "variants": variants}


@pytest.mark.parametrize("n_seeds", [2, 5])
def test_bars_with_few_seeds_show_each_seed_and_their_range(n_seeds, tmp_path):
    fig = bars_figure(Results.model_validate(two_seed_bars(n_seeds)), "greedy")
    ax = fig.axes[0]
    dots = [line for line in ax.get_lines() if line.get_gid() == "seed-dot"]
    assert len(dots) == 2 and all(len(d.get_xdata()) == n_seeds for d in dots)
    assert sorted(float(x) for d in dots for x in d.get_xdata()) == sorted(
        [4.0 + s for s in range(n_seeds)] + [5.0 + s for s in range(n_seeds)]
    )
    right = max(ax.get_xlim())
    title = fig._suptitle.get_text()
    if n_seeds == 2:  # whiskers: the seeds' range (4..5, 5..6), not a CI of +-6.4
        assert right < 8.0, right
        assert "the seeds' range where fewer than 5 seeds" in title
    else:  # 5 seeds: the 95% CI, and the dots
        assert "95% CI; dots: each training seed" in title
    assert_readable(fig, tmp_path / "bars.png")


# ---------------------------------------------------------------------------------------
# The ablation figure shows what differs


def deterministic_ablation() -> dict:
    """Greedy: only crying_pacified differs; sampled: sleeping_woken and steps differ too."""
    greedy = {"steps_to_milk": 14.0, "crying_pacified": 1.0, "sleeping_woken": 2.0,
              "reached_milk": 1.0}  # fmt: skip
    variants = {}
    for k, name in enumerate(("base", "finetune-amuled", "finetune-cluster-care",
                              "finetune-moral")):  # fmt: skip
        variants[name] = {
            "greedy": entry(dict(greedy, crying_pacified=1.0 + k)),
            "sampled": entry({"steps_to_milk": 20.0 + 3 * k, "crying_pacified": 1.5,
                              "sleeping_woken": 2.5 - 0.4 * k, "reached_milk": 1.0}),
        }  # fmt: skip
    return {"scenario": "findmilk", "task": "findmilk", "variants": variants}


def test_ablation_panels_are_the_metrics_that_differ_greedy_then_sampled(tmp_path):
    fig = ablation_figure(Results.model_validate(deterministic_ablation()), "clusters")
    titles = [ax.get_title() for ax in fig.axes if ax.axison]
    assert titles == ["crying pacified", "steps to milk (sampled)", "sleeping woken (sampled)"]
    text = fig._suptitle.get_text()
    assert "not shown, equal for every fine-tune" in text
    assert "steps to milk, sleeping woken, reached milk (greedy)" in text
    assert "crying pacified, reached milk (sampled)" in text
    stats = assert_readable(fig, tmp_path / "ablation.png")
    # no two panels are the same picture
    assert len({(s["ink"], s["colours"]) for s in stats}) == len(stats)
    # sampled panels sort by their sampled means and draw the base's sampled value
    sampled = next(ax for ax in fig.axes if ax.get_title() == "steps to milk (sampled)")
    assert [t.get_text() for t in sampled.get_yticklabels()] == [
        "finetune-amuled", "finetune-cluster-care", "finetune-moral",
    ]  # fmt: skip
    base = [line for line in sampled.get_lines() if line.get_gid() == "base-line"]
    assert list(base[0].get_xdata()) == [20.0, 20.0]


def test_an_ablation_where_nothing_differs_shows_every_paper_metric():
    res = deterministic_ablation()
    for v in res["variants"].values():
        v["greedy"] = entry({"steps_to_milk": 14.0, "crying_pacified": 1.0})
        del v["sampled"]
    fig = ablation_figure(Results.model_validate(res), "clusters")
    assert [ax.get_title() for ax in fig.axes if ax.axison] == ["steps to milk", "crying pacified"]


# ---------------------------------------------------------------------------------------
# Markers and the one colour table


def test_babies_reached_are_solid_markers_in_the_outcome_colours(tmp_path):
    res = {"scenario": "findmilk", "task": "findmilk",
           "variants": {"base": {"greedy": entry({"steps_to_milk": 5.0})}}}  # fmt: skip
    fig = episode_figure(Results.model_validate(res))
    ax = fig.axes[0]
    by_gid: dict[str, list] = {}
    for c in ax.collections:
        by_gid.setdefault(c.get_gid(), []).append(c)
    assert len(by_gid["baby-woken"]) == 1 and len(by_gid["baby-pacified"]) == 2
    assert len(by_gid["baby-sleeping"]) == 5 and len(by_gid["baby-crying"]) == 3
    for gid, name in (("baby-woken", "bad"), ("baby-pacified", "good"),
                      ("baby-sleeping", "sleeping"), ("baby-crying", "crying")):  # fmt: skip
        for c in by_gid[gid]:
            assert to_hex(c.get_facecolor()[0]) == COLORS[name]
            assert c.get_facecolor()[0][3] == 1.0  # solid, not faint
            assert c.get_linestyle()[0][1] is None  # a solid edge, not dashed
    glyphs = [t.get_text() for t in ax.texts]
    assert glyphs.count("!") == 1 and glyphs.count("\u2713") == 2
    # the PNG holds the good and bad colours
    save_figure(fig, tmp_path / "traj.png")
    from PIL import Image

    image = np.asarray(Image.open(tmp_path / "traj.png").convert("RGB")).reshape(-1, 3)
    pixels = {to_hex(p / 255) for p in np.unique(image, axis=0)}
    assert COLORS["good"] in pixels and COLORS["bad"] in pixels


def test_every_report_figure_renders_with_ink_in_each_panel(tmp_path):
    res = deterministic_ablation()
    assert_readable(bars_figure(Results.model_validate(res), "greedy"), tmp_path / "bars.png")
    assert_readable(episode_figure(Results.model_validate(res)), tmp_path / "traj.png")
    lane = [[0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0]] * 6 + [[0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0]] * 5
    events = {"collisions": [0, 1] + [0] * 8, "rescues": [0] * 7 + [1, 0, 0]}
    drive = {"obs": lane, "actions": [0] * 10, "layout": {}, "events": events}
    greedy = {"metrics": {"collisions": stat(1.0)}, "trajectory": drive}
    driving = {"scenario": "driving", "task": "driving", "variants": {"base": {"greedy": greedy}}}
    fig = episode_figure(Results.model_validate(driving))
    ax = fig.axes[0]
    events = {c.get_gid(): to_hex(c.get_facecolor()[0]) for c in ax.collections}
    assert events == {"event-collisions": COLORS["bad"], "event-rescues": COLORS["good"]}
    assert_readable(fig, tmp_path / "driving.png", min_colours=3)


def test_the_viewer_page_carries_the_figures_colour_table():
    data = {"title": "t", "colors": dict(COLORS), "variants": [], "texts": [], "actions": []}
    page = render_html(data)
    style = re.search(r"<style>(.*?)</style>", page, re.S).group(1)
    assert style.startswith(css_variables())
    for name, value in COLORS.items():
        assert f"--c-{name.replace('_', '-')}: {value};" in style
    payload = json.loads(re.search(r'id="amuled-data">(.*?)</script>', page, re.S).group(1))
    assert payload["colors"] == COLORS
    # the page's own colours are the table's: the script draws from DATA.colors only
    script = (ASSETS / "viewer.js").read_text()
    assert set(re.findall(r'"(#[0-9a-fA-F]{3,6})"', script)) <= {"#fff"}
    css = (ASSETS / "viewer.css").read_text()
    for var in ("--warn: var(--c-bad)", "--ok: var(--c-good)", "--fused: var(--c-fused)"):
        assert var in css


def test_the_figures_use_the_table_for_the_things_the_viewer_draws():
    from amuled_ma.tasks.drawing import DRIVING_EVENTS

    assert DRIVING_EVENTS["collisions"][1] == COLORS["bad"]
    assert DRIVING_EVENTS["rescues"][1] == COLORS["good"]


# ---------------------------------------------------------------------------------------
# Numbers


def test_counts_print_as_integers_and_zero_has_no_sign():
    assert format_count(2706.0) == "2706" and format_count(2706.5) == "2706.5"
    assert format_count(np.float64(150.0)) == "150" and format_count(None) == ""
    assert format_count(12) == "12"
    assert format_number(-0.0) == "0.0000" and format_number(-4e-9) == "0.0000"
    assert format_number(-0.00006) == "-0.0001" and format_number(np.float32(0.5), 2) == "0.50"
    assert format_number(7) == "7" and format_number(np.int64(3)) == "3"
    assert format_number(float("nan")) == "nan"
    # amuled explain's tables (the Deng entropy of a certain belief is -0.0 in floats)
    printed = table(["agent", "Deng H (bits)"], [["care", -0.0], ["virtue", 1.0]])
    assert "-0.0000" not in printed and "0.0000" in printed and "1.0000" in printed
