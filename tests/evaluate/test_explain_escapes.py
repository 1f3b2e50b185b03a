"""Terminal control sequences in an LLM reply are printed escaped by ``amuled explain``."""

from __future__ import annotations

import json
from pathlib import Path

from amuled_ma.cli import main
from amuled_ma.evaluate.explain import printable

OBS = [2, 3, 7, 7, 2, 2, 1, 1]
#: Clear the screen, write the clipboard (OSC 52), a hyperlink (OSC 8), a C1 CSI, a bidi
#: override and a carriage return that would overwrite the line.
HOSTILE = (
    "\x1b[2J\x1b[H"
    "\x1b]52;c;cm0gLXJmIH4=\x07"
    "\x1b]8;;http://evil.example/\x1b\\click\x1b]8;;\x1b\\"
    "\x9b31m\u202eevil\rX\x00"
)


def test_printable_escapes_every_control_character() -> None:
    shown = printable("ok " + HOSTILE + "\tend")
    assert shown.startswith("ok \\x1b[2J\\x1b[H\\x1b]52;c;cm0gLXJmIH4=\\x07")
    assert "\\x9b31m\\u202eevil\\x0dX\\x00\tend" in shown
    assert not any(ord(c) < 0x20 and c != "\t" for c in shown)
    assert not any(0x7F <= ord(c) <= 0x9F for c in shown)
    assert printable("plain text, ünïcödé") == "plain text, ünïcödé"


def test_explain_prints_hostile_replies_escaped(recordings_dir: Path, tmp_path: Path, capsys):
    data = json.loads((recordings_dir / "findmilk-gpt-4o-mini.json").read_text())
    hit = 0
    for state in data["states"]:
        if [round(x) for x in state["obs"]] == OBS:
            for exchange in state.get("exchanges") or []:
                exchange["response"] = HOSTILE + "\n" + exchange["response"]
                hit += 1
    assert hit, "the test state is not in the recording"
    hostile = tmp_path / "hostile.json"
    hostile.write_text(json.dumps(data))
    argv = [
        "explain", "findmilk", "--obs", ",".join(map(str, OBS)), "--prompt-var",
        "num_crying=4", "--full", "--set", f'feedback.recording="{hostile}"',
    ]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "\\x1b]52;c;cm0gLXJmIH4=\\x07" in out  # the reader sees what the reply held
    assert "\x1b" not in out and "\x9b" not in out and "\r" not in out and "\u202e" not in out
