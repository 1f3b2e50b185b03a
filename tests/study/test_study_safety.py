"""What a study folder, a participant's request or a command line may make the study do.

The server sends only regular files inside the study folder; request bodies are read by
bounded models (a bad one is 400 with a short JSON reason, never a 500); the export's cells
cannot run in a spreadsheet; ``study.json`` nested too deep is one line; ``serve`` binds
this machine only unless told ``--public``, names a port in use, and refuses the template's
placeholders; the report warns of too few participants and says why alpha is n/a; the
state pictures use the colour table of the report and the viewer; ``build`` names a missing
run folder before importing torch. Each test runs on a hand-written study (no training).
"""

from __future__ import annotations

import csv
import io
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from starlette.testclient import TestClient
from study_fixtures import ROOT, free_port, hand_study
from tiny_cli import one_line

from amuled_ma.cli import main
from amuled_ma.study.analysis import answers_csv
from amuled_ma.study.answers import Answer, AnswerStore, read_refusals
from amuled_ma.study.drawing import driving_svg, findmilk_svg
from amuled_ma.study.report import write_analysis
from amuled_ma.study.server import StudyApp
from amuled_ma.tasks.colors import COLORS

#: A regression would serve forever (the server started): fail instead.
pytestmark = pytest.mark.timeout(120)

TEMPLATE = ROOT / "amuled_ma" / "study" / "templates" / "consent.html"


def serve_refusal(folder: Path, capsys, *extra: str) -> str:
    """``amuled study serve FOLDER`` refused: its one error line (nothing served first)."""
    capsys.readouterr()
    assert main(["study", "serve", str(folder), "--port", str(free_port()), *extra]) == 1
    out, err = capsys.readouterr()
    assert "serving on" not in out
    return one_line(err)


# ---------------------------------------------------------------------------------------
# the folder's files: regular files inside it, never a link


def test_a_linked_picture_consent_page_or_states_folder_is_refused_at_the_start(tmp_path, capsys):
    secret = tmp_path / "secret.txt"
    secret.write_text("root:x:0:0:root:/root:/bin/bash\n")
    folder = hand_study(tmp_path / "a")
    picture = folder / "states" / "q001.svg"
    picture.unlink()
    picture.symlink_to(secret)
    assert serve_refusal(folder, capsys) == (
        f"amuled: error: {picture}: the state picture must be a regular file inside the "
        f"study folder, found a symbolic link to {secret}; replace it by the file itself "
        "(rebuild the study with 'amuled study build')"
    )
    folder = hand_study(tmp_path / "b")
    consent = folder / "consent.html"
    consent.unlink()
    consent.symlink_to(secret)
    assert f"{consent}: the consent page must be a regular file" in serve_refusal(folder, capsys)
    # a linked states/ folder: each picture is a regular file, outside the study folder
    folder = hand_study(tmp_path / "c")
    shutil.move(folder / "states", tmp_path / "elsewhere")
    (folder / "states").symlink_to(tmp_path / "elsewhere")
    line = serve_refusal(folder, capsys)
    assert line.startswith(f"amuled: error: {folder / 'states' / 'q001.svg'}: the state picture")
    assert f"it resolves to {(tmp_path / 'elsewhere' / 'q001.svg').resolve()}" in line
    # a FIFO is not a regular file (and is not waited on)
    folder = hand_study(tmp_path / "d")
    (folder / "consent.html").unlink()
    os.mkfifo(folder / "consent.html")
    assert "consent page must be a regular file inside the study folder, found a FIFO" in (
        serve_refusal(folder, capsys)
    )


def test_a_consent_page_turned_into_a_link_while_serving_is_404_and_sends_nothing(tmp_path, capsys):
    secret = tmp_path / "secret.txt"
    secret.write_text("root:x:0:0:root:/root:/bin/bash\n")
    folder = hand_study(tmp_path / "s")
    study = StudyApp(folder)
    with TestClient(study.app) as client:
        assert client.get("/consent").text == "<p>my own words</p>"
        (folder / "consent.html").unlink()
        (folder / "consent.html").symlink_to(secret)
        answer = client.get("/consent")
        assert answer.status_code == 404
        assert "root:" not in answer.text and str(folder) not in answer.text
    assert "symbolic link" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------
# request bodies: bounded at the edge, 400 with a short reason, never 500


def test_a_lone_surrogate_a_huge_integer_or_a_nan_is_400_never_500(tmp_path):
    folder = hand_study(tmp_path / "s")
    study = StudyApp(folder)
    huge = "1" * 5001
    with TestClient(study.app, raise_server_exceptions=False) as client:
        me = client.post("/api/session", json={}).json()
        own = f'"participant": "{me["participant"]}", "token": "{me["token"]}", "item": "q001"'
        sent = {
            "/api/session": [
                b'{"participant": "\\ud800"}',
                f'{{"participant": {huge}}}'.encode(),
                b'{"participant": "' + b"x" * 201 + b'"}',
                b'{"participant": "p\xff"}',
                b"[" * 1000 + b"]" * 1000,
                b'{"participant": "PROLIFIC-1", "extra": 1}',
            ],
            "/api/answer": [
                b'{"participant": "\\udfff", "token": "t", "item": "q001"}',
                f'{{{own}, "choice": "A", "ms": {huge}, "ratings": {{"A": 1, "B": 2}}}}'.encode(),
                f'{{{own}, "choice": "A", "ms": NaN, "ratings": {{"A": 1, "B": 2}}}}'.encode(),
                f'{{{own}, "choice": "A", "ms": 5, "ratings": {{"A": {huge}, "B": 2}}}}'.encode(),
                f'{{{own}, "choice": "A", "ms": 5, "ratings": {{"A": true, "B": 2}}}}'.encode(),
            ],
        }
        for path, bodies in sent.items():
            for body in bodies:
                answer = client.post(path, content=body)
                assert answer.status_code == 400, (body[:80], answer.text)
                error = answer.json()["error"]
                assert isinstance(error, str) and 0 < len(error) < 500
        ok = f'{{{own}, "choice": "A", "ms": 5, "ratings": {{"A": 1, "B": 2}}}}'.encode()
        assert client.post("/api/answer", content=ok).status_code == 200
    reasons = [r[3] for r in read_refusals(folder / "answers.sqlite")]
    # pydantic's parser refuses an integer of over 4,300 digits with the whole body
    malformed = "answer: missing or malformed field"
    assert reasons == [malformed, malformed, "bad time", malformed, "rating outside the scale"]


# ---------------------------------------------------------------------------------------
# the export: no cell a spreadsheet runs


def test_the_export_neutralises_formulas_and_control_characters(tmp_path):
    folder = hand_study(tmp_path)
    ids = {
        '=HYPERLINK("http://evil.example","click")': '\'=HYPERLINK("http://evil.example","click")',
        "@SUM(1+1)|cmd": "'@SUM(1+1)|cmd",
        "+1": "'+1",
        "-2": "'-2",
        "\tx": "'\\x09x",
        "\rx": "'\\x0dx",
        "a\x1b[31mb\x07": "a\\x1b[31mb\\x07",
        "plain-id": "plain-id",
    }
    store = AnswerStore(folder / "answers.sqlite")
    for n, pid in enumerate(ids):
        store.participant(pid, "participant")
        store.add(Answer(pid, "q001", "A", "base", None, 900.0 + n, 1.0e9, 3, 4))
    store.close()
    text = answers_csv(folder)
    body = text.replace("\n", "")
    assert not any(ord(c) < 32 or 127 <= ord(c) < 160 for c in body)
    rows = list(csv.reader(io.StringIO(text)))
    assert sorted(row[0] for row in rows[1:]) == sorted(ids.values())
    assert rows[1][10:12] != ["", ""]  # numbers stay numbers
    assert {row[-2] for row in rows[1:]} == {"3"}


# ---------------------------------------------------------------------------------------
# study.json nested too deep


def test_a_deeply_nested_study_file_is_one_line_in_analyze_and_serve(tmp_path, capsys):
    folder = hand_study(tmp_path / "s")
    path = folder / "study.json"
    path.write_text('{"items": ' + "[" * 100_000 + "]" * 100_000 + "}")
    for command in (["study", "analyze", str(folder)],
                    ["study", "serve", str(folder), "--port", str(free_port())]):  # fmt: skip
        assert main(command) == 1
        line = one_line(capsys.readouterr().err)
        assert line.startswith(f"amuled: error: {path}: not JSON (")
        assert "recursion limit exceeded" in line and line.endswith("rebuild the study")


# ---------------------------------------------------------------------------------------
# where the server listens


def test_every_interface_needs_public_and_a_port_in_use_is_one_line(tmp_path, capsys):
    folder = hand_study(tmp_path / "s")
    (folder / "consent.html").write_text("<p>my own words</p>")
    for host in ("", "0.0.0.0"):
        line = serve_refusal(folder, capsys, "--host", host)
        assert line.startswith(f"amuled: error: --host {host or repr(host)}: not a loopback ")
        assert "pass --public" in line
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        capsys.readouterr()
        assert main(["study", "serve", str(folder), "--port", str(port)]) == 1
        out, err = capsys.readouterr()
    assert "serving on" not in out
    assert one_line(err) == (
        f"amuled: error: --port {port}: port {port} of 127.0.0.1 is in use (another server, or "
        f"this study served already?); pass a free one with --port N (e.g. --port {port + 1})"
    )


def test_public_serves_every_interface_with_one_warning_line(tmp_path):
    folder = hand_study(tmp_path / "s")
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "amuled_ma", "study", "serve", str(folder), "--host", "0.0.0.0",
         "--public", "--port", str(port)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert server.stderr.readline() == (
            "amuled: warning: serving on 0.0.0.0: any machine that can reach this one can "
            "open the study and post answers\n"
        )
        assert server.stdout.readline().startswith(f"study {folder}: serving on http://0.0.0.0:")
        for _ in range(100):
            try:
                answer = httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=1)
                break
            except httpx.TransportError:
                time.sleep(0.05)
        assert answer.json() == {"ok": True, "items": 1}
    finally:
        server.kill()
        server.wait()


# ---------------------------------------------------------------------------------------
# the consent page's placeholders


def test_the_template_s_placeholders_stop_the_start_unless_allowed(tmp_path, capsys):
    folder = hand_study(tmp_path / "s")
    shutil.copy(TEMPLATE, folder / "consent.html")
    assert serve_refusal(folder, capsys) == (
        f"amuled: error: {folder / 'consent.html'}: the consent page still holds the "
        "template's placeholders [N], [Say how the data are kept, for how long, and who sees "
        "them.], [name, institution, contact e-mail]; write the study's own text there, or "
        "pass --allow-placeholder-consent to serve it as it is (a trial run)"
    )
    StudyApp(folder, allow_placeholder_consent=True).store.close()
    # the researcher's own text, with a citation in brackets: served
    (folder / "consent.html").write_text("<p>Dr A. Smith, Uni X [1]; 10 minutes.</p>")
    StudyApp(folder).store.close()


# ---------------------------------------------------------------------------------------
# the report: too few participants, and why alpha is n/a


def answered(folder: Path, choices: dict[str, str]) -> None:
    store = AnswerStore(folder / "answers.sqlite")
    for pid, choice in choices.items():
        store.participant(pid, "participant")
        store.add(Answer(pid, "q001", choice, "base" if choice == "A" else "amuled", None,
                         900.0, 1.0e9, 3, 4))  # fmt: skip
    store.close()


def test_the_report_warns_of_few_participants_and_says_why_alpha_is_missing(tmp_path, capsys):
    folder = hand_study(tmp_path / "one")
    answered(folder, {"p1": "A"})
    warned: list[str] = []
    report = write_analysis(folder, warn=warned.append).read_text()
    assert warned == [
        "only 1 participants: the 95% intervals (bootstrap over participants) are unreliable "
        "below 10 and one person moves every estimate; gather more answers before drawing "
        "conclusions"
    ]
    assert f"**Warning:** {warned[0]}." in report
    assert "choices A/B over the pairs): n/a (fewer than 2 raters (1))." in report
    folder = hand_study(tmp_path / "same")
    answered(folder, {"p1": "A", "p2": "A", "p3": "A"})
    capsys.readouterr()
    assert main(["study", "analyze", str(folder)]) == 0
    err = capsys.readouterr().err
    assert err.startswith("amuled: warning: only 3 participants:") and err.count("\n") == 1
    report = (folder / "analysis" / "report.md").read_text()
    assert "n/a (no variation: every answer has the same value)" in report
    folder = hand_study(tmp_path / "ten")
    answered(folder, {f"p{i}": "AB"[i % 2] for i in range(10)})
    warned.clear()
    report = write_analysis(folder, warn=warned.append).read_text()
    assert warned == [] and "Warning" not in report
    # ten raters of one item, 5 A and 5 B: alpha is defined and shown. By Krippendorff's
    # coincidences, one unit of m = 10 values: D_o = sum_{c != k} o_ck / n = (2 * 25 / 9) / 10
    # = 5/9 and D_e = sum_{c != k} n_c n_k / (n (n - 1)) = 50 / 90 = 5/9, so alpha = 1 - 1 = 0
    line = next(x for x in report.splitlines() if "choices A/B over the pairs" in x)
    assert line.endswith("pairs): 0.000.")


# ---------------------------------------------------------------------------------------
# the pictures: the report's and the viewer's colours and glyphs


def colours(svg: str) -> set[str]:
    return set(re.findall(r'(?:fill|stroke)="([^"]+)"', svg))


def test_the_study_pictures_use_the_colour_table_and_the_viewer_s_glyphs():
    svg = findmilk_svg(8, [1, 2], [6, 6], [[3, 3], [5, 1]], [[0, 7]])
    white = {"#ffffff", "#fff", "white"}
    assert colours(svg) <= set(COLORS.values()) | white
    crying = re.findall(
        r'<g class="crying"><circle [^>]*fill="([^"]+)"[^>]*/><text[^>]*>C</text>', svg
    )
    sleeping = re.findall(
        r'<g class="sleeping"><rect [^>]*fill="([^"]+)"[^>]*/><text[^>]*>z</text>', svg
    )
    assert crying == [COLORS["crying"]] * 2 and sleeping == [COLORS["sleeping"]]
    assert 'class="milk" points="' in svg and f'fill="{COLORS["milk"]}"' in svg
    assert re.search(rf'class="robot"[^>]*fill="{COLORS["agent"]}"', svg)
    road = driving_svg(5, 8, 2, [[1, 3]], [[4, 5]])
    assert colours(road) <= set(COLORS.values()) | white
    assert re.search(rf'class="car"[^>]*fill="{COLORS["car"]}"', road)
    assert re.search(rf'class="grandma"[^>]*fill="{COLORS["grandma"]}"', road)
    assert re.search(rf'class="agent"[^>]*fill="{COLORS["agent"]}"', road)
    assert f'fill="{COLORS["road"]}"' in road


# ---------------------------------------------------------------------------------------
# build: a missing run folder, named before torch is imported


def test_build_names_a_missing_run_folder_before_importing_torch(tmp_path):
    script = (
        "import sys; from amuled_ma.cli import main; "
        f"rc = main(['study', 'build', {str(tmp_path / 'nope')!r}, '--out', "
        f"{str(tmp_path / 'out')!r}]); print(rc, 'torch' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})  # fmt: skip
    assert done.stdout.split() == ["1", "False"]  # refused, and torch never imported
    assert one_line(done.stderr) == (
        f"amuled: error: {tmp_path / 'nope'}: the run folder does not exist; give a run "
        "folder of 'amuled run' or 'amuled train' (is the path right?)"
    )
    assert not (tmp_path / "out").exists()
