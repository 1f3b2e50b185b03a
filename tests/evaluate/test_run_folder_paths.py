"""``amuled evaluate`` and ``amuled view`` write no file through a link, and read none.

A link named ``report.md``, ``results.json``, ``results.csv`` or a figure in a run folder,
pointing at a file outside, is refused with one line before the first episode, and the
outside file keeps its bytes; ``amuled view -o`` refuses a FIFO, a device node and a link,
which keep their ``st_mode``; a linked ``results.json`` or ``feedback.json`` is not read.
"""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

import pytest
from tiny_cli import RULES, TINY

from amuled_ma.cli import main
from amuled_ma.evaluate.report.curves import load_curves
from amuled_ma.files.safe import UnsafePathError


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny trained base policy (no evaluation yet)."""
    run = tmp_path_factory.mktemp("paths") / "findmilk"
    assert main(["train", "findmilk", "--run-dir", str(run), *TINY, *RULES]) == 0
    return run


@pytest.fixture
def run(trained: Path, tmp_path: Path) -> Path:
    """A copy of the trained run, the test's own."""
    return Path(shutil.copytree(trained, tmp_path / "run"))


def error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("amuled: error:")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize("name", ["report.md", "results.json", "results.csv", "metrics_greedy.png"])
def test_evaluate_refuses_a_linked_output_and_the_outside_file_is_unchanged(
    run: Path, tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    outside = tmp_path / "outside.bin"
    outside.write_bytes(b"the user's file")
    (run / name).symlink_to(outside)
    capsys.readouterr()
    argv = ["evaluate", str(run), "--episodes", "1", "--modes", "greedy", "--no-progress"]
    assert main(argv) == 1
    line = error_line(capsys)
    assert f"{run / name}: is a symbolic link (to {outside})" in line
    assert outside.read_bytes() == b"the user's file"
    # refused before the evaluation: none of the other outputs was written
    others = {"report.md", "results.json", "results.csv", "metrics_greedy.png"} - {name}
    assert [n for n in sorted(others) if (run / n).exists()] == []


def test_view_refuses_a_fifo_a_device_and_a_link_as_its_output(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fifo = tmp_path / "page.fifo"
    os.mkfifo(fifo)
    outside = tmp_path / "outside.html"
    outside.write_text("kept")
    link = tmp_path / "page.html"
    link.symlink_to(outside)
    targets = [fifo, link]
    if os.geteuid() == 0:
        full = tmp_path / "full"
        os.mknod(full, stat.S_IFCHR | 0o666, os.makedev(1, 7))  # what /dev/full is
        targets.append(full)
    for target in targets:
        before = os.lstat(target).st_mode
        capsys.readouterr()
        assert main(["view", str(run), "--variant", "base", "-o", str(target)]) == 1
        line = error_line(capsys)
        assert f"{target}: is a" in line and "not a regular file" in line
        assert os.lstat(target).st_mode == before
    assert outside.read_text() == "kept"


def test_a_linked_results_file_is_not_read(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    outside = tmp_path / "results.json"
    outside.write_text('{"episodes": 5}')
    (run / "results.json").symlink_to(outside)
    capsys.readouterr()
    assert main(["view", str(run), "--variant", "base"]) == 1
    line = error_line(capsys)
    assert f"{run / 'results.json'}: is a symbolic link" in line
    assert "does not follow links in a run folder" in line


def test_a_linked_feedback_file_is_not_read(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    outside = tmp_path / "feedback.json"
    outside.write_text("{}")
    (run / "base" / "feedback.json").symlink_to(outside)
    capsys.readouterr()
    argv = ["evaluate", str(run), "--episodes", "1", "--modes", "greedy", "--no-progress"]
    assert main(argv) == 1
    assert f"{run / 'base' / 'feedback.json'}: is a symbolic link" in error_line(capsys)
    assert not (run / "results.json").exists()


def test_a_linked_variant_folder_is_not_read(run: Path, tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "curve.json").write_text("[]")
    (run / "other").symlink_to(elsewhere)
    with pytest.raises(UnsafePathError, match="outside its folder"):
        load_curves(run)


def test_run_refuses_a_linked_report_before_training(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    outside = tmp_path / "notes.md"
    outside.write_text("mine")
    (run / "report.md").symlink_to(outside)
    capsys.readouterr()
    assert main(["run", "findmilk", "--run-dir", str(run), *TINY, *RULES, "--resume"]) == 1
    assert f"{run / 'report.md'}: is a symbolic link (to {outside})" in error_line(capsys)
    assert outside.read_text() == "mine"
    assert sorted(p.name for p in run.iterdir() if p.is_dir()) == ["base"]  # nothing trained


def test_the_demo_live_section_replaces_the_old_one_and_follows_no_link(
    tmp_path: Path,
) -> None:
    from amuled_ma.commands._demo_live import LIVE_HEADING, put_live_section

    run = tmp_path / "run"
    run.mkdir()
    (run / "report.md").write_text(f"# Report\n\n{LIVE_HEADING}\n\nold leg\n", encoding="utf-8")
    put_live_section(run, [LIVE_HEADING, "", "new leg", ""])
    assert (run / "report.md").read_text(encoding="utf-8") == (
        f"# Report\n\n{LIVE_HEADING}\n\nnew leg\n"
    )
    outside = tmp_path / "notes.md"
    outside.write_text("mine")
    (run / "report.md").unlink()
    (run / "report.md").symlink_to(outside)
    with pytest.raises(UnsafePathError, match="does not follow links"):
        put_live_section(run, [LIVE_HEADING, "", "new leg", ""])
    assert outside.read_text() == "mine"
