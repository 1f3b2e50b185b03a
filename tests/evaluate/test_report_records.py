"""Every report statement about a variant comes from its run record (``config.json``).

The records below are written by hand, or by the run folder's own writer from a checkpoint
made here with known ``infos``; each expected sentence follows from those numbers.
"""

from __future__ import annotations

import pytest
import torch
from report_tables import rows_of
from sparse_files import sparse

from amuled_ma.evaluate.report.describe import panels_table, settings_table
from amuled_ma.evaluate.report.writing import write_report
from amuled_ma.evaluate.results import Results
from amuled_ma.experiments.run_folder import read_record, variant_fields, write_config
from amuled_ma.records.run_record import RunRecord
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import Scenario

SHA = "0f" * 32
PAPER = ["consequentialist", "deontological", "virtue", "care", "social_justice"]


def stat(mean: float) -> dict:
    return {"mean": mean, "half_width": 0.5, "n": 5, "std": 0.5,
            "ci_low": mean - 0.5, "ci_high": mean + 0.5}  # fmt: skip


def results(*tunes: str) -> Results:
    """base and the fine-tunes, every greedy metric equal to base's."""
    entry = {"greedy": {"metrics": {"rescues": stat(2.0), "collisions": stat(1.0)}}}
    return Results.model_validate(
        {"scenario": "driving", "task": "driving", "episodes": 5, "confidence": 0.95,
         "seed": 7, "variants": {"base": entry, **dict.fromkeys(tunes, entry)}}
    )  # fmt: skip


def training(**feedback) -> dict:
    return {
        "variant": "finetune:amuled",
        "seed": 1,
        "iterations": 20,
        "finetune": {"recipe": "authors", "lambda_kl": 0.05},
        "feedback": {
            "source": "replay",
            "recording": "driving-gpt-4o-mini.json",
            "clusters": PAPER,
            "fusion": "bjs-dst",
            **feedback,
        },
        "inputs": {"recording_sha256": SHA},
    }


def test_an_interrupted_fine_tune_is_shown_interrupted_with_its_iteration(tmp_path):
    folder = tmp_path / "finetune-amuled"
    fields = variant_fields(Variant.parse("finetune:amuled"), folder, training())
    write_config(folder, Scenario().to_dict(), fields)
    # its checkpoint: stopped before its first iteration of 20
    infos = {"iteration": 0, "total_iterations": 20, "completed": False}
    torch.save({"infos": infos}, folder / "model_last.pt")
    record = read_record(folder)
    assert (record.state, record.iterations_done, record.iterations_planned) == (
        "interrupted", 0, 20,
    )  # fmt: skip
    records = {"finetune-amuled": record}
    rows = rows_of(settings_table(results("finetune-amuled"), None, records))
    assert rows["fine-tune iterations"] == ["interrupted at 0 of 20"]
    assert rows_of(panels_table({"finetune-amuled": record}))["finetune-amuled"][3] == (
        "interrupted at 0 of 20"
    )
    text = write_report(tmp_path, results("finetune-amuled"), records=records).read_text()
    assert "finetune-amuled is interrupted at iteration 0 of 20" in text
    assert "its training interrupted at iteration 0 of 20" in text
    assert "a strong KL anchor" not in text  # not explained as the anchor's doing
    assert "| 20 |" not in text

    # finished: the checkpoint says so, and the record follows
    infos = {"iteration": 20, "total_iterations": 20, "completed": True}
    torch.save({"infos": infos}, folder / "model_last.pt")
    record = read_record(folder)
    assert (record.state, record.iterations_done) == ("complete", 20)
    rows = rows_of(settings_table(results("finetune-amuled"), None, {"finetune-amuled": record}))
    assert rows["fine-tune iterations"] == ["20"]


def test_a_recording_of_fused_beliefs_only_is_named_as_such(tmp_path, recordings_dir):
    from amuled_ma.beliefs.sources.replay import Recording
    from amuled_ma.deliberation.panel_feedback import FusedReplayFeedback

    recording = Recording(recordings_dir / "driving-gpt-4o-mini.json")
    assert recording.fused_only  # the authors kept only the fused belief (docs/authors.md)
    feedback = FusedReplayFeedback(recording, "zero")
    folder = tmp_path / "finetune-amuled"
    fields = variant_fields(Variant.parse("finetune:amuled"), folder, training(),
                            feedback=feedback)  # fmt: skip
    record = RunRecord.model_validate(fields)
    assert record.panel.fused_only and record.panel.members == [] and record.panel.fusion is None
    rows = rows_of(settings_table(results("finetune-amuled"), None, {"finetune-amuled": record}))
    assert rows["panel"][0].startswith("none asked: the fused beliefs the authors recorded")
    assert "bjs-dst" not in rows["panel"][0]
    assert rows["beliefs from"] == [
        "replay of `driving-gpt-4o-mini.json`, fused beliefs only (the authors' recording)"
    ]
    assert rows["recording"] == [f"`driving-gpt-4o-mini.json` (fused beliefs only) sha256 `{SHA}`"]
    row = rows_of(panels_table({"finetune-amuled": record}))["finetune-amuled"]
    assert row[4:7] == [
        "none asked: the recorded fused belief",
        "replay of `driving-gpt-4o-mini.json`, fused beliefs only (the authors' recording)",
        "the authors' (recorded)",
    ]


def test_each_fine_tune_shows_its_own_panel():
    one = training(clusters=["care", "virtue"])
    two = training(clusters=["care", "deontological"], fusion="mean")
    records = {
        name: RunRecord.model_validate(
            variant_fields(Variant.parse("finetune:amuled", name[9:]), name, data)
        )
        for name, data in (("finetune-a", one), ("finetune-b", two))
    }
    rows = rows_of(settings_table(results("finetune-a", "finetune-b"), None, records))
    assert rows["panel"] == [
        "finetune-a: care, virtue; fusion `bjs-dst`; finetune-b: care, deontological; fusion `mean`"
    ]
    panels = rows_of(panels_table(records))
    assert panels["finetune-a"][4] == "care, virtue" and panels["finetune-a"][6] == "bjs-dst"
    assert panels["finetune-b"][4] == "care, deontological" and panels["finetune-b"][6] == "mean"


def test_a_config_json_over_4_mb_is_refused_unread_with_one_line(tmp_path):
    from amuled_ma.errors import AmuledError
    from amuled_ma.experiments.run_folder import MAX_RECORD_BYTES

    assert MAX_RECORD_BYTES == 4_000_000
    folder = tmp_path / "finetune-amuled"
    fields = variant_fields(Variant.parse("finetune:amuled"), folder, training())
    write_config(folder, Scenario().to_dict(), fields)
    path = folder / "config.json"
    assert read_record(folder) is not None and path.stat().st_size < 20_000  # about 6 KB
    sparse(path, 10**10)
    with pytest.raises(AmuledError) as info:
        read_record(folder)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: the run record is 10,000,000,000 bytes, more than the ")
    assert "4,000,000 a run record may be" in message and "--force" in message


def test_a_config_json_that_is_not_utf8_is_one_line(tmp_path):
    from amuled_ma.errors import AmuledError

    folder = tmp_path / "base"
    folder.mkdir()
    (folder / "config.json").write_bytes(b'{"x": "\xff"}')
    with pytest.raises(AmuledError, match="not a readable config") as info:
        read_record(folder)
    assert "\n" not in str(info.value)
