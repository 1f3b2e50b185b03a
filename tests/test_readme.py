"""The README is true: every command in it runs (or is skipped with its reason), every path exists.

Each ``amuled`` command of the README's ``bash`` blocks has an entry in :data:`HOW`: ``run``
(run here as written, in a fresh folder), ``tiny`` (run as written plus the tests' tiny
budget, :data:`tiny_cli.TINY`, where it would train for minutes), or the reason it is not
run. A command added to the README without an entry fails :func:`test_every_command_has_an_entry`.
Every command, run or not, must parse with the real command line.
"""

from __future__ import annotations

import re
import shlex

import pytest
from tiny_cli import REPO, TINY

from amuled_ma.cli import build_parser, main

README = REPO / "README.md"
#: What the README may not say: issue numbers, this project's build-machine folders.
FORBIDDEN = (r"\bissue \d+", r"\.\./shared", r"/work/", r"#\d{2,}\b")

LONG = "trains for minutes at full length"
#: How each README command is checked (the README's text, continuation lines joined).
HOW: dict[str, str] = {
    "amuled demo": "needs the network (the authors' files, first time) and the Ollama build; "
    "tests/integration/test_live_demo.py runs it",
    "amuled --help": "run",
    "amuled run findmilk --quick": "tests/test_cli_quick.py runs the short form at the tests' "
    "tiny budget",
    "amuled ablate findmilk --what aggregation --quick": "tiny",
    "amuled run findmilk --recipe authors --seeds 5": LONG,
    "amuled run driving": LONG,
    "amuled ablate findmilk --what clusters": LONG,
    "amuled ablate findmilk --what budget": LONG,
    "amuled train findmilk --variant base": "tiny",
    "amuled finetune findmilk --feedback amuled": "tiny",
    "amuled evaluate runs/findmilk": "run",
    "amuled view runs/findmilk": "run",
    "amuled explain findmilk --obs 0,0,7,7,2,2,1,1": "run",
    "amuled beliefs stats --store runs/findmilk/beliefs.sqlite": "run",
    "amuled clusters list --clusters-dir examples/my_clusters": "run",
    "amuled clusters show care --task findmilk": "run",
    "amuled ollama up --tiny": "needs the Ollama build and the tiny model "
    "(tests/integration run the private server)",
    "amuled finetune findmilk --set feedback.source=ollama --set feedback.model=amuled-tiny": (
        "needs a live Ollama server (tests/integration/test_live_ollama.py)"
    ),
    "amuled ollama down": "stops the server 'ollama up' started; not started here",
    "amuled import authors ../moral_agent": "needs a clone of the authors' repository "
    "(tests/authors import a fake one)",
    "amuled evaluate runs/authors/findmilk": "needs 'amuled import authors' first",
}
#: The order the ``run``/``tiny`` commands must run in (later ones read earlier ones' runs).
ORDER = (
    "amuled train findmilk --variant base",
    "amuled finetune findmilk --feedback amuled",
    "amuled evaluate runs/findmilk",
    "amuled view runs/findmilk",
    "amuled beliefs stats --store runs/findmilk/beliefs.sqlite",
)


def bash_lines() -> list[str]:
    """Every command line of the README's ``bash`` blocks, continuations joined."""
    lines: list[str] = []
    for block in re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S):
        lines += [line for line in block.replace("\\\n", " ").splitlines() if line.strip()]
    return lines


def readme_commands() -> list[str]:
    """The ``amuled`` commands of :func:`bash_lines` (after ``&&`` and inside ``$(...)`` too)."""
    found: list[str] = []
    for line in bash_lines():
        inner = re.findall(r"\$\(([^)]*)\)", line)
        outer = re.sub(r"\$\([^)]*\)", "X", line)
        parts = [shlex.split(part, comments=True) for part in (*outer.split("&&"), *inner)]
        for words in parts:
            if words and words[0] in ("amuled", ".venv/bin/amuled"):
                found.append(shlex.join(["amuled", *words[1:]]))
    return found


def test_the_readme_is_short_and_names_no_build_machine_or_issue():
    text = README.read_text()
    assert len(text.splitlines()) <= 200
    for pattern in FORBIDDEN:
        assert not re.search(pattern, text), pattern
    assert "--quick" in text  # the short form is documented


def test_every_path_and_link_it_names_exists():
    text = README.read_text()
    named = set(re.findall(r"\]\(([^)#\s]+)", text))  # markdown links, anchors dropped
    named |= set(
        re.findall(r"(?<![\w./-])((?:docs|scenarios|examples|prompts|\.ci)/[\w./-]*)", text)
    )
    named = {n.rstrip(".,") for n in named if not n.startswith(("http://", "https://"))}
    assert {"docs/viewer.png", "scenarios/findmilk-demo.toml", ".ci/setup"} <= named
    missing = sorted(n for n in named if not (REPO / n).exists())
    assert not missing, missing
    # each anchor link into the README itself names one of its headings
    headings = {
        re.sub(r"[^\w -]", "", h).strip().lower().replace(" ", "-")
        for h in re.findall(r"^#+ (.+)$", text, flags=re.M)
    }
    for anchor in re.findall(r"\]\(#([\w-]+)\)", text):
        assert anchor in headings, anchor


def test_every_command_has_an_entry():
    assert sorted(set(readme_commands())) == sorted(HOW)
    assert set(ORDER) <= {c for c, how in HOW.items() if how in ("run", "tiny")}


@pytest.mark.parametrize("command", sorted(HOW))
def test_every_command_parses(command):
    parser = build_parser()
    try:
        parser.parse_args(shlex.split(command)[1:])
    except SystemExit as stop:  # --help exits 0; a usage error exits 2
        assert stop.code == 0, command


def run(command: str, capsys: pytest.CaptureFixture[str]) -> str:
    """Run a README command (with the tiny budget where :data:`HOW` says), its output."""
    args = shlex.split(command)[1:]
    if HOW[command] == "tiny":
        args += [*TINY, "--set", "evaluation.episodes=2"]
        if args[0] in ("run", "ablate"):
            args += ["--jobs", "1"]  # in this process: no local Ray to start
    try:
        code = main(args)
    except SystemExit as stop:  # --help
        code = stop.code
    out, err = capsys.readouterr()
    assert code == 0, f"{command}: {err}"
    return out


def test_the_commands_run(tmp_path, monkeypatch, capsys, recordings_dir):
    monkeypatch.chdir(tmp_path)  # the README's relative paths (runs/findmilk) land here
    (tmp_path / "examples").symlink_to(REPO / "examples")  # and the checkout's own
    monkeypatch.setenv("AMULED_RECORDINGS", str(recordings_dir))
    outputs = {command: run(command, capsys) for command in ORDER}
    assert (tmp_path / "runs/findmilk/report.md").is_file()
    assert (tmp_path / "runs/findmilk/view-episode0.html").is_file()
    assert "finetune findmilk/finetune-amuled: done" in outputs[ORDER[1]]
    for command, how in sorted(HOW.items()):
        if how in ("run", "tiny") and command not in ORDER:
            assert run(command, capsys).strip(), command
    ablation = tmp_path / "runs/findmilk-quick/ablate-aggregation/report.md"
    assert "NOT the paper's length" in ablation.read_text().splitlines()[0]


def test_what_it_says_of_the_demo_matches_the_code():
    from amuled_ma.authors.pinned import BASE_POLICIES, PINNED
    from amuled_ma.scenario import load_scenario

    text = " ".join(README.read_text().split())
    # the sizes fetched the first time: the recording the demo replays and the base
    demo = load_scenario("findmilk-demo")
    recording = next(pin for pin in PINNED if pin.recording == demo.feedback.recording)
    base = BASE_POLICIES["findmilk"]
    assert f"({recording.size / 1e6:.1f} MB and {base.size / 1e3:.0f} kB)" in text
    assert f"{demo.finetune.iterations} fine-tuning iterations instead of the paper's" in text
    assert f"base (ours, {demo.base.total_steps:,} steps)" in text
    # the viewer caption quotes what the page shows for a replayed recording
    viewer = (REPO / "amuled_ma/evaluate/viewer.js").read_text()
    assert '"reasoning: not kept"' in text and '"reasoning: not kept"' in viewer
