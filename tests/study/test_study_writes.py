"""What the study commands write: whole files, never through a link, nothing but regular files.

``study build``, ``study analyze``, ``study export -o`` and ``study fit-weights`` each
refuse, with one line and before any work, an output that is a symbolic link (to a file
outside the study) or a FIFO; the file a link points to keeps its bytes, and nothing else
is written. Each test runs on a hand-written study (no training, no run).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from study_fixtures import hand_study
from tiny_cli import one_line

from amuled_ma.cli import main
from amuled_ma.study.answers import Answer, AnswerStore

SECRET = "root:x:0:0:root:/root:/bin/bash\n"


def _answered(folder: Path) -> Path:
    """The hand study with three participants' answers (enough for an analysis)."""
    store = AnswerStore(folder / "answers.sqlite")
    for pid, choice in {"p1": "A", "p2": "B", "p3": "A"}.items():
        store.participant(pid, "participant")
        store.add(Answer(pid, "q001", choice, "base" if choice == "A" else "amuled", None,
                         900.0, 1.0e9, 3, 4))  # fmt: skip
    store.close()
    return folder


def _secret(tmp_path: Path) -> Path:
    secret = tmp_path / "secret.txt"
    secret.write_text(SECRET)
    return secret


def _refused(argv: list[str], capsys) -> str:
    capsys.readouterr()
    assert main(argv) == 1
    return one_line(capsys.readouterr().err)


def test_analyze_refuses_a_linked_output_or_folder_and_writes_nothing(tmp_path, capsys):
    secret = _secret(tmp_path)
    folder = _answered(hand_study(tmp_path / "s"))
    (folder / "analysis").mkdir()
    (folder / "analysis" / "report.md").symlink_to(secret)
    line = _refused(["study", "analyze", str(folder)], capsys)
    report = folder / "analysis" / "report.md"
    assert line.startswith(f"amuled: error: {report}: is a symbolic link")
    assert secret.read_text() == SECRET
    # checked before the first file: summary.json and the figure are not written either
    assert sorted(p.name for p in (folder / "analysis").iterdir()) == ["report.md"]
    # a linked analysis/ folder would put every output outside the study
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (folder / "analysis" / "report.md").unlink()
    (folder / "analysis").rmdir()
    (folder / "analysis").symlink_to(elsewhere)
    line = _refused(["study", "analyze", str(folder)], capsys)
    assert line.startswith(f"amuled: error: {folder / 'analysis'}: is a symbolic link (to ")
    assert list(elsewhere.iterdir()) == []
    # a regular analysis folder: the three outputs are written
    (folder / "analysis").unlink()
    assert main(["study", "analyze", str(folder)]) == 0
    assert sorted(p.name for p in (folder / "analysis").iterdir()) == [
        "report.md",
        "strengths.png",
        "summary.json",
    ]


def test_export_refuses_a_link_or_a_fifo_before_reading_the_answers(tmp_path, capsys):
    secret = _secret(tmp_path)
    folder = _answered(hand_study(tmp_path / "s"))
    link = tmp_path / "answers.csv"
    link.symlink_to(secret)
    line = _refused(["study", "export", str(folder), "-o", str(link)], capsys)
    assert line.startswith(f"amuled: error: {link}: is a symbolic link (to {secret})")
    assert secret.read_text() == SECRET and link.is_symlink()
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    line = _refused(["study", "export", str(folder), "-o", str(fifo)], capsys)
    assert "is a FIFO (named pipe), not a regular file" in line
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    # a new file: the answers are written
    out = tmp_path / "new.csv"
    assert main(["study", "export", str(folder), "-o", str(out)]) == 0
    assert out.read_text().count("\n") == 4  # the header and three answers


def test_fit_weights_refuses_a_linked_output_before_fitting(tmp_path, capsys):
    secret = _secret(tmp_path)
    folder = hand_study(tmp_path / "s")  # no answers: a fit would be refused for that
    (folder / "analysis").mkdir()
    (folder / "analysis" / "weights.json").symlink_to(secret)
    line = _refused(["study", "fit-weights", str(folder)], capsys)
    assert line.startswith(
        f"amuled: error: {folder / 'analysis' / 'weights.json'}: is a symbolic link (to {secret})"
    )
    assert secret.read_text() == SECRET


def test_build_refuses_linked_outputs_before_reading_the_runs(tmp_path, capsys):
    secret = _secret(tmp_path)
    run = tmp_path / "run"
    run.mkdir()  # an empty run folder: the build would fail on it after the outputs' check
    out = tmp_path / "study"
    out.mkdir()
    (out / "study.json").symlink_to(tmp_path / "nowhere.json")  # dangling: not "a study"
    argv = ["study", "build", str(run), "--out", str(out), "--items", "1"]
    line = _refused(argv, capsys)
    assert line.startswith(f"amuled: error: {out / 'study.json'}: is a symbolic link (to ")
    assert not (tmp_path / "nowhere.json").exists()
    (out / "study.json").unlink()
    (out / "consent.html").symlink_to(secret)
    line = _refused(argv, capsys)
    assert line.startswith(f"amuled: error: {out / 'consent.html'}: is a symbolic link (to ")
    (out / "consent.html").unlink()
    elsewhere = tmp_path / "pictures"
    elsewhere.mkdir()
    (elsewhere / "mine.svg").write_text("<svg/>")
    (out / "states").symlink_to(elsewhere)
    line = _refused(argv, capsys)
    assert line.startswith(f"amuled: error: {out / 'states'}: is a symbolic link (to {elsewhere})")
    assert [p.name for p in elsewhere.iterdir()] == ["mine.svg"]
    assert secret.read_text() == SECRET
