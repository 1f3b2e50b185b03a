"""The report of the authors' imported policies says what they are: imported, from which file.

``amuled import authors`` on a folder laid out like their checkout (``authors_fakes``:
``base.cleanrl_model`` and ``moral_llm_gpt-4o-mini/ppo_{5,10,100}``), then ``amuled
evaluate``. The expected file names and the iteration 100 are the fake checkout's, written
by hand there; the seed 42 is the ``_42`` of the authors' folder names.
"""

from authors_fakes import fake_checkout

from amuled_ma.cli import main


def rows_of(text: str, heading: str) -> dict[str, list[str]]:
    """The rows of the first Markdown table after ``heading`` (or of the whole text)."""
    lines = text.split("\n")
    start = lines.index(heading) if heading in lines else 0
    table = [line for line in lines[start:] if line.startswith("|")]
    end = next((i for i, line in enumerate(table) if i and not line), len(table))
    out = {}
    for line in table[2:end]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        out.setdefault(cells[0], cells[1:])
    return out


def test_the_report_of_imported_policies_says_they_are_imported(tmp_path):
    checkout = tmp_path / "moral_agent"
    fake_checkout(checkout)
    argv = ["import", "authors", str(checkout), "--runs", str(tmp_path / "runs"),
            "--to", str(tmp_path / "rec")]  # fmt: skip
    assert main(argv) == 0
    run = tmp_path / "runs" / "authors" / "findmilk"
    assert main(["evaluate", str(run), "--episodes", "2", "--no-progress"]) == 0
    report = (run / "report.md").read_text()
    # nothing of a fine-tune trained here: no recipe, no lambda_KL, no "no fine-tune"
    assert "equation" not in report
    assert "lambda_KL" not in report.split("## Metrics")[0]
    assert "2.5" not in report.split("## Metrics")[0]
    assert "No fine-tuned variant" not in report
    settings = rows_of(report, "## Settings")
    assert settings["training seeds"] == ["1: 42"]
    imported = settings["imported policies"][0]
    assert "base: `models/FindMilk-v4_42/base.cleanrl_model`" in imported
    assert (
        "amuled-gpt-4o-mini: `models/FindMilk-v4_42/moral_llm_gpt-4o-mini/ppo_100.cleanrl_model`"
        ", checkpoint iteration 100" in imported
    )
    table = [line for line in report.split("\n") if line.startswith("| amuled-gpt-4o-mini |")]
    assert table[0].startswith(
        "| amuled-gpt-4o-mini | fine-tune on the authors' LLM panel (gpt-4o-mini) | "
        "`models/FindMilk-v4_42/moral_llm_gpt-4o-mini/ppo_100.cleanrl_model` | 100 |"
    )
    # the fine-tune is named as such where its diagnostics would be
    assert "No fine-tune of this run recorded fused-belief diagnostics" in report
